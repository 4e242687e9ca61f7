"""BabyAI navigation levels (minigrid's GoToLocal, GoToObjMaze, GoTo) as a planner task.

Layouts come from minigrid itself (``episode.py``: a reset minigrid level turned into arrays);
the dynamics are a jax.numpy port of minigrid's (``env.py``, ``view.py``), tested step for step
against minigrid (``check_port.py``, tests/test_babyai_port.py).
"""
from __future__ import annotations
