"""The Kuka world for the baselines of ``diffplan.baselines`` (the paper's Table 2 BC).

As the paper's appendix describes them, the baselines see the world as our planner does (the
condition channels of :mod:`envs.kuka.task`: the top block's colour and the stack height of
every cell) and the instruction as a vector of the instructed constraints (:func:`goal_vector`:
one entry per ordered pair of blocks "top on bottom", one for "one tower of all four"), and the
task is decomposed into single pick-and-place moves: the network picks a cell to pick from and
a cell to place on (two heads of 24 x 24 = 576 cells each), and the move is executed by the same
primitive and physics as the planner's (``KukaTask.step``: the block on top at the pick cell is
carried around the base, ``grid.arc_points``, the expert's carry, and placed on whatever is at
the place cell), re-observed after every placement.

BC learns the training expert's moves (``envs.kuka.training``: the instructed relations in
instruction order, the same expert the denoiser learns from) in the states between placements
that the denoiser's training draws (``training.training_state``, perturbed as there), on the
same task specs (the four Table 2 columns, canonical and training-paraphrase instructions).
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from diffplan import language
from diffplan.baselines import bc, nets
from diffplan.baselines.policies import PolicyWorld
from envs.kuka import expert, grammar, grid, primitive, scene
from envs.kuka.task import Action, NUM_COND_CHANNELS, condition_from_view
from envs.kuka.training import SPECS, spec_examples, training_state

PAIRS = np.array([(top, bottom) for top in range(scene.NUM_BLOCKS)
                  for bottom in range(scene.NUM_BLOCKS) if top != bottom], np.int32)
"""The ordered block pairs (top, bottom) of the goal vector's relation entries (12)."""
GOAL_DIM = len(PAIRS) + 1
"""A multi-hot entry per pair "top on bottom", then "one tower of all four blocks"."""
NUM_CELLS = grid.GRID_SIZE * grid.GRID_SIZE
HEADS = 2
"""The action: a pick cell and a place cell, NUM_CELLS choices each."""
MAX_SENTENCES = grammar.MAX_RELATIONS + 1
STOP_ID = grammar.VOCABULARY.word_to_id["."]


def split_sentences(tokens):
    """int32 (MAX_SENTENCES, SENTENCE_TOKENS): the sentences of instruction tokens int (L,),
    one per row (each ends with its full stop), padded with 0; words beyond a row's length and
    sentences beyond MAX_SENTENCES are dropped. jit-able."""
    tokens = jnp.asarray(tokens, jnp.int32)
    index = jnp.arange(tokens.shape[0])
    stop = tokens == STOP_ID
    sentence = jnp.cumsum(stop) - stop
    last_stop = jax.lax.cummax(jnp.where(stop, index, -1))
    start = jnp.concatenate([jnp.zeros((1,), jnp.int32), last_stop[:-1] + 1])
    position = index - start
    keep = tokens != language.PAD_ID
    rows = jnp.where(keep, sentence, MAX_SENTENCES)  # out of range: dropped
    out = jnp.zeros((MAX_SENTENCES, grammar.SENTENCE_TOKENS), jnp.int32)
    return out.at[rows, position].set(tokens, mode="drop")


def _sentence_meaning(row):
    """(top token, bottom token, tower bool) of one sentence: the slots of whichever of the
    grammar's relation phrasings it is (held-out ones included: the parser is written by hand,
    not learned), the tower sentence's flag; for any other sentence, its first two colour
    words as (top, bottom) (0 where absent)."""
    index, slots = language.match_template(row, grammar.RELATIONS)
    tower_index, _ = language.match_template(row, grammar.TOWERS)
    is_colour = (row >= grammar.block_token(0)) & (row <= grammar.block_token(scene.NUM_BLOCKS - 1))
    order = jnp.argsort(jnp.where(is_colour, jnp.arange(row.shape[0]), row.shape[0]))
    first = jnp.where(is_colour[order[0]], row[order[0]], 0)
    second = jnp.where(is_colour[order[1]], row[order[1]], 0)
    matched = index >= 0
    tower = tower_index >= 0
    top = jnp.where(matched, slots[0], jnp.where(tower, 0, first))
    bottom = jnp.where(matched, slots[1], jnp.where(tower, 0, second))
    return top, bottom, tower


def instruction_relations(tokens):
    """(relations int32 (MAX_SENTENCES, 2) (top, bottom) block indices, -1 rows where a sentence
    names no relation; tower bool ()): what an instruction int (L,) asks for."""
    top, bottom, tower = jax.vmap(_sentence_meaning)(split_sentences(tokens))
    valid = (top > 0) & (bottom > 0) & (top != bottom)
    relations = jnp.stack([top, bottom], -1) - grammar.block_token(0)
    return jnp.where(valid[:, None], relations, -1).astype(jnp.int32), jnp.any(tower)


def _goal_vector_one(tokens):
    relations, tower = instruction_relations(tokens)
    hot = jnp.any(jnp.all(relations[:, None, :] == jnp.asarray(PAIRS)[None], -1), 0)
    return jnp.concatenate([hot, tower[None]]).astype(jnp.float32)


def goal_vector(tokens):
    """float32 (..., GOAL_DIM): the multi-hot constraint vector of instruction tokens
    int (..., L) (:data:`PAIRS` entries, then the tower entry)."""
    tokens = jnp.asarray(tokens, jnp.int32)
    flat = tokens.reshape((-1, tokens.shape[-1]))
    return jax.vmap(_goal_vector_one)(flat).reshape(tokens.shape[:-1] + (GOAL_DIM,))


def input_shapes() -> dict:
    """The (condition, goal) network's input shapes, as its checkpoints record them."""
    return {"condition": [1, grid.GRID_SIZE, grid.GRID_SIZE, NUM_COND_CHANNELS],
            "goal": [1, GOAL_DIM]}


def net_config(**overrides) -> nets.ConvNetConfig:
    """The appendix's network with the Kuka action's two cell heads."""
    return nets.ConvNetConfig(**{"num_outputs": HEADS * NUM_CELLS, **overrides})


# ------------------------------------------------------------------------------- actions

def cell_index(cell):
    """int32 (): the flat index of a cell int (2,)."""
    return (cell[0] * grid.GRID_SIZE + cell[1]).astype(jnp.int32)


def actions_of(indices):
    """task.Action with a leading batch axis from flat (pick, place) cell indices int (B, 2):
    the cells, carried around the base between the two cells' centres (the primitive replaces
    the ends by the picked block's and the support's positions)."""
    indices = jnp.asarray(indices, jnp.int32)
    cells = jnp.stack([indices // grid.GRID_SIZE, indices % grid.GRID_SIZE], -1)  # (B, 2, 2)

    def one(c):
        waypoints = grid.arc_points(grid.cell_center(c[0]), grid.cell_center(c[1]),
                                    primitive.NUM_WAYPOINTS)
        return Action(cells=c.reshape(4), waypoints=waypoints.astype(jnp.float32))

    return jax.vmap(one)(cells)


# ------------------------------------------------------------------------------- BC

def bc_example(key, spec, perturb_prob: float = 0.5):
    """(condition float32 (24, 24, 2), goal vector float32 (GOAL_DIM,), action int32 (2,)):
    a training state (``training.training_state``) and the training expert's next move there,
    as flat (pick, place) cell indices of the blocks' centre cells."""
    pos, quat, episode = training_state(key, spec, perturb_prob)
    held = jnp.zeros(scene.NUM_BLOCKS, bool)
    step = expert.decide(pos, held, episode)
    top, height = grid.top_down_view(pos, quat, held)
    action = jnp.stack([cell_index(step.action[:2]), cell_index(step.action[2:])])
    return condition_from_view(top, height), goal_vector(episode.tokens), action


def bc_batch(key, batch_size: int, specs=SPECS, perturb_prob: float = 0.5):
    """(conditions (B, 24, 24, 2), goal vectors (B, GOAL_DIM), actions int32 (B, 2)): the same
    share of every task spec (batch_size a multiple of len(specs)); training-stream keys."""
    return spec_examples(bc_example, key, batch_size, specs, perturb_prob)


def specs_data(specs=SPECS) -> dict:
    """The training data's description recorded in a run's metadata."""
    return {"specs": [[s.kind, s.multi, s.language] for s in specs]}


def train_bc(out_dir: str, config: bc.BCTrainConfig = bc.BCTrainConfig(batch_size=128),
             net: nets.ConvNetConfig | None = None, specs=SPECS, progress: bool = True):
    """diffplan.baselines.bc.train_bc on :func:`bc_batch` (config.batch_size a multiple of
    len(specs))."""
    return bc.train_bc(out_dir, functools.partial(bc_batch, specs=specs), input_shapes(),
                       config, net or net_config(), data=specs_data(specs), progress=progress)


POLICY_WORLD = PolicyWorld(goal_fn=goal_vector, goal_dim=GOAL_DIM, heads=HEADS,
                           action_fn=actions_of)
"""How the trained baselines act in the Kuka world (``diffplan.baselines.policies``)."""
