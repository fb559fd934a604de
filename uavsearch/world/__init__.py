"""The world: procedural city scenes (scene), their seed splits (settings), the PyBullet camera (render)
and top-down maps (topdown)."""
