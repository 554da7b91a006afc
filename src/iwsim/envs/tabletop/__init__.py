"""What the tabletop tasks share: the scene (camera, walls, the two pushers, their speed
limit), its colour model, scripting and the Task base."""
