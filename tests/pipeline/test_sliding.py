"""The frame window both the denoise command and the progressive loop stream through."""
from torchmanifold.pipeline.sliding import SlidingFrames


def test_each_frame_made_and_prepared_once_and_released_behind_the_window():
    made, prepared = [], []
    frames = SlidingFrames(lambda k: made.append(k) or f"frame {k}",
                           lambda k, fr: prepared.append(k) or f"state of {fr}", {0: "frame 0"})
    for t in range(6):  # +-1 windows, as a streamed clip asks for them
        ids = list(range(max(0, t - 1), min(6, t + 2)))
        assert frames.prepared(ids) == [f"state of frame {k}" for k in ids]
        assert frames.frames(ids) == [f"frame {k}" for k in ids]
        assert sorted(frames._frames) == ids and sorted(frames._prepared) == ids  # nothing behind is held
    assert made == [1, 2, 3, 4, 5] and prepared == [0, 1, 2, 3, 4, 5] and frames.served == 6
    frames.forget_prepared()
    assert frames.prepared([4, 5]) == ["state of frame 4", "state of frame 5"] and prepared[-2:] == [4, 5]
    assert made == [1, 2, 3, 4, 5]  # frames stay: only what was derived from them is recomputed
