"""Browser teleoperation of a world model (``iwsim play``): an engine that steps every
session at a fixed control rate in shared forward passes, a FastAPI/WebSocket server and
one static page (keyboard, mouse, gamepad; record, save, discard; side by side with MuJoCo)."""
