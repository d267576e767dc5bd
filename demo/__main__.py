"""``python -m demo [--headless --frames N --screenshot FILE.png] [options]``: see ``--help``."""
import sys

from demo.app import run


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        app = run(argv)
    except ValueError as exc:  # bad option values: one clear line, no traceback
        print(f"demo: error: {exc}", file=sys.stderr)
        return 2
    st = app.stage_summary()
    if st:
        print(f"{st['iterations_per_second']:.2f} iterations/s; median ms: trace {st['trace_ms']:.1f} (waited "
              f"{st['trace_wait_ms']:.1f})  filter {st['filter_ms']:.1f}  display {st['display_ms']:.1f}  "
              f"({app.frames_drawn} frames, {app.tracer.width}x{app.tracer.height}, clip {len(app.frame_times)})")
    if app.argv.screenshot:
        print(f"saved {app.argv.screenshot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
