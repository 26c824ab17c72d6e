"""``presim teleop``: drive a robot from a browser page (live colour + depth, a top-down map, keyboard
and on-screen controls, recording). ``protocol`` validates what the page sends (pure functions),
``frames`` turns simulator output into what the page shows, ``session`` runs the simulator in a thread,
``server`` serves the page and its WebSocket (starlette + uvicorn, 127.0.0.1 by default)."""
