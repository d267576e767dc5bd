"""Real-time demo of torchmanifold: progressive path tracing filtered with adaptive manifolds.

``python -m demo`` opens the window; ``python -m demo --headless --frames N --screenshot out.png``
renders N frames without a display and saves the final window image.
"""
