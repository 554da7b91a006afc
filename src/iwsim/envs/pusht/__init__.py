"""Bimanual T-pushing (``iwsim/BimanualPushT-v0``): the MuJoCo simulator, the T's geometry,
the pixel scorer, the scripted policies and the Task."""
