"""BabyAI navigation levels (minigrid's GoToLocal, GoToObjMaze, GoTo) as a planner task.

Layouts come from minigrid itself (``episode.py``: a reset minigrid level turned into arrays);
the dynamics are a jax.numpy port of minigrid's (``env.py``, ``view.py``), tested step for step
against minigrid (``check_port.py``, tests/test_babyai_port.py).
"""
from __future__ import annotations


def make(level: str, **overrides):
    """(BabyAITask, generate: key -> Episode) of a level (``goto_local``, ``goto_obj_maze``,
    ``goto`` or its minigrid id). Overrides naming a ``BabyAITask`` field (path_weight,
    subgoal_weight, cell_id_base) go to the task, the others to ``BabyAIConfig`` (pad_multiple,
    max_tokens, tokenizer); unknown names raise a ValueError.

    ``generate`` resets minigrid on the host through ``jax.pure_callback`` (jit- and vmap-able;
    the seed comes from the key's bits, ``envs.babyai.seeds.key_seed``): unlike the grid
    world's, it is not a pure jax function. Evaluation and training reset minigrid with the
    seeds of ``envs.babyai.seeds`` (``episode.layouts``)."""
    from envs.babyai.config import BabyAIConfig, make_config
    from envs.babyai.episode import make_generate
    from envs.babyai.task import BabyAITask
    from envs.overrides import split_overrides

    parts = split_overrides(f"babyai/{level}", overrides,
                            task=(BabyAITask, {"config", "num_cond_channels",
                                               "num_gen_channels"}),
                            config=(BabyAIConfig, {"level"}))
    config = make_config(level, **parts["config"])
    return BabyAITask(config, **parts["task"]), make_generate(config)
