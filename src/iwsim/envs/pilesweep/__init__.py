"""Pile sweeping (``iwsim/PileSweep-v0``): the MuJoCo simulator, the pixel scorer (pieces in
the tray, counted from a frame), the scripted policies and the Task."""
