"""The Kuka world for the baselines of ``diffplan.baselines`` (the paper's Table 2 BC, CQL and
DD).

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

CQL (the appendix's: reward minus the distance to the current target, the block to pick, then
the place) needs transitions, and physics is far too slow to make 300k of them on a CPU: its
decision process (:class:`KukaCollector`) moves blocks as the primitive places them, at rest,
without physics, from the same training states. A move is two decisions over the 576 cells,
the pick's and then the place's, one Q-value per cell; the network's goal input also says which
decision it is and which block the pick took (:func:`decision_goals`), and the policy makes the
two greedily in turn (:func:`q_decide`). It is evaluated like BC, in physics.

The DD-style planner diffuses over block states (:func:`block_frame`: the four blocks' centres,
which it observes from the physics, :func:`observe_blocks`): 4-frame trajectories of the
training expert's next placements made without physics (:func:`dd_example`), conditioned on the
constraint vector; its inverse dynamics maps two consecutive frames to the pick and place cells
(two heads), and the move is executed in physics like the others'.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from diffplan import language
from diffplan.baselines import bc, cql, dd, nets
from diffplan.baselines.policies import PolicyWorld
from envs.kuka import env, expert, grammar, grid, physics, primitive, scene
from envs.kuka.task import Action, NUM_COND_CHANNELS, condition_from_view, view_of_condition
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
    grammar's relation phrasings it is (development and sealed held-out ones included: the
    parser is written by hand, not learned), the tower sentence's flag; for any other
    sentence, its first two colour words as (top, bottom) (0 where absent)."""
    index, slots = language.match_template(row, grammar.RELATIONS)
    tower_index, _ = language.match_template(row, grammar.TOWERS)
    is_colour = grammar.is_block_token(row)
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

def move_cells(cells):
    """int32 (2,): the flat (pick, place) cell indices of an action's cells int (4,)
    (:func:`actions_of`'s inverse on the cells)."""
    return grid.cell_index(jnp.asarray(cells).reshape(2, 2).T)


def actions_of(indices):
    """task.Action with a leading batch axis from flat (pick, place) cell indices int (B, 2):
    the cells, carried around the base between the two cells' centres (the primitive replaces
    the ends by the picked block's and the support's positions)."""
    cells = grid.cell_of(indices)  # (B, 2, 2)

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
    action = move_cells(step.action)
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


# ------------------------------------------------------------------------------- CQL

Q_GOAL_DIM = GOAL_DIM + scene.NUM_BLOCKS + 1
"""CQL's goal input: the constraint vector, then which block the pick took (one-hot, zeros when
it took none) and 1 when the decision is the place (0: the pick)."""


def place_poses(pos, quat, block, cell):
    """(pos float32 (4, 3), quat float32 (4, 4)): ``block`` (int (), -1: nothing) put down at
    cell int (2,) where the primitive puts it (``env.place_of``: centred on the highest
    other block covering the cell, else on the floor at the cell's centre), at rest, flat and
    turned as its support (unturned on the floor): the move without physics."""
    pos, quat = jnp.asarray(pos, jnp.float32), jnp.asarray(quat, jnp.float32)
    place, _, support = env.place_of(pos, quat, jnp.zeros(scene.NUM_BLOCKS, bool), block, cell)
    turned = jnp.where(support >= 0, quat[jnp.maximum(support, 0)],
                       jnp.array([1.0, 0.0, 0.0, 0.0]))
    centre = place.at[2].set(place[2] - scene.BLOCK_HALF_SIZE[2] - primitive.PLACE_GAP)
    b = jnp.maximum(block, 0)
    moved = block >= 0
    return (pos.at[b].set(jnp.where(moved, centre, pos[b])),
            quat.at[b].set(jnp.where(moved, turned, quat[b])))


@struct.dataclass
class QState:
    """A state of CQL's decision process (one episode): blocks at rest at pos float32 (4, 3),
    quat (4, 4); placing bool () (False: the next decision is the cell to pick from, True: the
    cell to place on); block int32 () the block the pick took (-1: none); target int32 (2,) the
    flat cells of the training expert's pick and place from the last state between placements
    (the reward's targets); reward float32 () of the last decision; t int32 () placements made;
    episode (its goal: ``training.planner_goal``)."""

    pos: jax.Array
    quat: jax.Array
    placing: jax.Array
    block: jax.Array
    target: jax.Array
    reward: jax.Array
    t: jax.Array
    episode: Any


def _expert_cells(pos, episode):
    """int32 (2,): the flat pick and place cells of the training expert's next move."""
    step = expert.decide(pos, jnp.zeros(scene.NUM_BLOCKS, bool), episode)
    return move_cells(step.action)


def _cell_distance(a, b):
    """float32 (): metres between the centres of flat cells a and b."""
    return jnp.linalg.norm(
        grid.cell_center(grid.cell_of(a)) - grid.cell_center(grid.cell_of(b)))


@dataclasses.dataclass(frozen=True)
class KukaCollector:
    """diffplan.baselines.cql.Collector of the Kuka world without physics: a decision is a cell
    (NUM_CELLS actions), the pick's, then the place's, made as the primitive makes them
    (:func:`place_poses`, the picked block being the one on top at the pick cell); the reward
    is minus the distance (m) from the chosen cell to the current target (the training expert's
    block to pick, then its place); an episode starts in a training state of one of the specs
    (``training.training_state``, the specs in equal shares), terminates when its relations
    hold between placements and is truncated after its max_steps placements. Instructions are
    stored as the multi-hot constraint vector int8 (GOAL_DIM,)."""

    specs: tuple = SPECS
    perturb_prob: float = 0.5
    num_actions: int = NUM_CELLS

    def episodes(self, key, n: int):
        return spec_examples(training_state, key, n, self.specs, self.perturb_prob)

    def reset(self, start):
        pos, quat, episode = start
        return QState(pos=pos, quat=quat, placing=jnp.zeros((), bool),
                      block=jnp.full((), -1, jnp.int32),
                      target=_expert_cells(pos, episode),
                      reward=jnp.zeros((), jnp.float32), t=jnp.zeros((), jnp.int32),
                      episode=episode)

    def instruction(self, start):
        return goal_vector(start[2].tokens).astype(jnp.int8)

    def step(self, state: QState, action):
        action = jnp.asarray(action, jnp.int32)
        cell = grid.cell_of(action)
        top, _ = grid.top_down_view(state.pos, state.quat)
        target = jnp.where(state.placing, state.target[1], state.target[0])
        reward = -_cell_distance(action, target)
        pos, quat = place_poses(state.pos, state.quat, state.block, cell)
        picked = state.replace(placing=jnp.ones((), bool), block=top[cell[0], cell[1]],
                               reward=reward)
        placed = state.replace(pos=pos, quat=quat, placing=jnp.zeros((), bool),
                               block=jnp.full((), -1, jnp.int32),
                               target=_expert_cells(pos, state.episode), reward=reward,
                               t=state.t + 1)
        return jax.tree.map(lambda a, b: jnp.where(state.placing, a, b), placed, picked)

    def observe(self, state: QState):
        return {"pos": state.pos, "quat": state.quat, "placing": state.placing,
                "block": state.block.astype(jnp.int8)}

    def expert_action(self, state: QState):
        return jnp.where(state.placing, state.target[1], state.target[0])

    def reward(self, state: QState):
        return state.reward

    def terminal(self, state: QState):
        nothing = jnp.zeros(scene.NUM_BLOCKS, bool)
        return ~state.placing & env.goal_reached_poses(state.pos, nothing, state.episode)

    def done(self, state: QState):
        return self.terminal(state) | (state.t >= state.episode.max_steps)


def decision_goals(goals, block, placing):
    """float32 (B, Q_GOAL_DIM): CQL's goal inputs of constraint vectors (B, GOAL_DIM), the
    block the pick took int (B,) (-1: none) and placing bool (B,)."""
    placing = jnp.asarray(placing, jnp.float32)
    taken = jax.nn.one_hot(block, scene.NUM_BLOCKS) * placing[:, None]
    return jnp.concatenate([jnp.asarray(goals, jnp.float32), taken, placing[:, None]], -1)


def q_inputs(stored, instruction):
    """The Q-network's (conditions (B, 24, 24, 2), goal inputs (B, Q_GOAL_DIM)) of stored
    observations (KukaCollector.observe) and constraint vectors int8 (B, GOAL_DIM): the view
    of the blocks as they rest (the picked one still in it, as a policy sees it before it
    moves)."""
    conditions = jax.vmap(lambda p, q: condition_from_view(*grid.top_down_view(p, q)))(
        stored["pos"], stored["quat"])
    return conditions, decision_goals(instruction, stored["block"].astype(jnp.int32),
                                      stored["placing"])


def q_decide(q_fn, conditions, goals):
    """task.Action (B leading): CQL's greedy move: the pick cell of the highest Q-value, then
    the place cell of the highest Q-value given the block on top at the pick cell (q_fn(goal
    inputs (B, Q_GOAL_DIM)) -> (B, NUM_CELLS) on the conditions (B, 24, 24, 2))."""
    b = goals.shape[0]
    none = jnp.zeros((b,), bool)
    pick = jnp.argmax(q_fn(decision_goals(goals, jnp.full((b,), -1), none)), -1)
    top, _ = view_of_condition(conditions)
    block = top.reshape(b, -1)[jnp.arange(b), pick]
    place = jnp.argmax(q_fn(decision_goals(goals, block, ~none)), -1)
    return actions_of(jnp.stack([pick, place], -1))


def q_input_shapes() -> dict:
    """The Q-network's input shapes, as its checkpoints record them."""
    return {**input_shapes(), "goal": [1, Q_GOAL_DIM]}


def train_cql(out_dir: str, config: cql.CQLTrainConfig = cql.CQLTrainConfig(),
              net: nets.ConvNetConfig | None = None, specs=SPECS, progress: bool = True,
              buffer=None):
    """diffplan.baselines.cql.train_cql with the :class:`KukaCollector` of the specs
    (config.collectors a multiple of len(specs)); the network has one Q-value per cell."""
    return cql.train_cql(out_dir, ((KukaCollector(tuple(specs)), 1),), q_inputs,
                         q_input_shapes(), config,
                         net or nets.ConvNetConfig(num_outputs=NUM_CELLS),
                         data=specs_data(specs), progress=progress, buffer=buffer)


Q_POLICY_WORLD = PolicyWorld(goal_fn=goal_vector, goal_dim=Q_GOAL_DIM, decide=q_decide)
"""How the trained CQL acts in the Kuka world (two greedy decisions: :func:`q_decide`)."""


# ------------------------------------------------------------------------------- DD-style

DD_HORIZON = 4
"""Frames of a DD-style trajectory: the blocks now and after each of the (at most 3) placements
of the training expert's plan (the last frame repeated once its goal holds)."""
FRAME_DIM = 3 * scene.NUM_BLOCKS
FRAME_SCALE = np.array([grid.HALF_EXTENT, grid.HALF_EXTENT, 8 * scene.BLOCK_HALF_SIZE[2]],
                       np.float32)
"""A frame is the block centres divided by these (x and y by the grid's half extent, z by four
block heights): values within [-1, 1]."""


def block_frame(pos):
    """float32 (..., FRAME_DIM): the DD-style planner's state of block centres pos (..., 4, 3)."""
    pos = jnp.asarray(pos, jnp.float32)
    return (pos / FRAME_SCALE).reshape(pos.shape[:-2] + (FRAME_DIM,))


def frame_pos(frame):
    """float32 (..., 4, 3): the block centres of frames (..., FRAME_DIM) (block_frame's inverse)."""
    frame = jnp.asarray(frame, jnp.float32)
    return frame.reshape(frame.shape[:-1] + (scene.NUM_BLOCKS, 3)) * FRAME_SCALE


def observe_blocks(state):
    """The DD-style planner's observation of a physical state: its block frame (FRAME_DIM,)
    (block poses, as Decision Diffuser's Kuka state; more than the planner's top-down view)."""
    return block_frame(physics.block_pos(state.data))


def dd_example(key, spec, perturb_prob: float = 0.5):
    """(trajectory float32 (FRAME_DIM, DD_HORIZON), goal vector (GOAL_DIM,), actions int32
    (DD_HORIZON - 1, 2) the expert's flat (pick, place) cells between consecutive frames, moves
    bool (DD_HORIZON - 1,) which of them are placements still needed): a training state
    (``training.training_state``) and the training expert's placements from there, made as the
    primitive makes them (:func:`place_poses`, no physics)."""
    pos, quat, episode = training_state(key, spec, perturb_prob)
    nothing = jnp.zeros(scene.NUM_BLOCKS, bool)
    frames, actions, moves = [block_frame(pos)], [], []
    for _ in range(DD_HORIZON - 1):
        step = expert.decide(pos, nothing, episode)
        move = ~env.goal_reached_poses(pos, nothing, episode)
        placed, turned = place_poses(pos, quat, step.block, step.action[2:])
        pos = jnp.where(move, placed, pos)
        quat = jnp.where(move, turned, quat)
        frames.append(block_frame(pos))
        actions.append(move_cells(step.action))
        moves.append(move)
    return (jnp.stack(frames, -1), goal_vector(episode.tokens), jnp.stack(actions),
            jnp.stack(moves))


def dd_trajectories(key, batch_size: int, specs=SPECS, perturb_prob: float = 0.5):
    """(trajectories float32 (B, FRAME_DIM, DD_HORIZON), goal vectors (B, GOAL_DIM)): the
    DD-style diffusion model's data (``dd.DDBatchFn``), every spec the same share."""
    return spec_examples(dd_example, key, batch_size, specs, perturb_prob)[:2]


def id_batch(key, batch_size: int, specs=SPECS, perturb_prob: float = 0.5):
    """(frames (B, FRAME_DIM), next frames (B, FRAME_DIM), expert cells int32 (B, 2)): one
    needed placement of each example, uniform among them (every training state needs one)."""
    traj, _, actions, moves = spec_examples(dd_example, key, batch_size, specs, perturb_prob)
    u = jax.random.uniform(jax.random.fold_in(key, 1), (batch_size,))
    j = jnp.floor(u * moves.sum(-1)).astype(jnp.int32)
    rows = jnp.arange(batch_size)
    return traj[rows, :, j], traj[rows, :, j + 1], actions[rows, j]


DD_CHANGE_WEIGHT = 0.0
"""The DD-style loss's extra weight of the entries that differ from frame 0
(``dd.DDTrainConfig.change_weight``): none here. By the last frame most of the 12 values differ,
and the grid world's 50 left the blocks that do not move free to drift in sampled frames: on
validation (seed 1000, 64 episodes per column, placements made without physics) 50 solved
0 / 19 / 0 / 2% of the four columns, 0 solved 83 / 100 / 67 / 59%."""


def dd_config(**overrides):
    """The Kuka DD-style planner's temporal UNet (4 frames of 12 values: a kernel of 3)."""
    return dd.DDConfig(**{"horizon": DD_HORIZON, "cells": FRAME_DIM, "kernel": 3, **overrides})


def id_config(**overrides):
    """Its inverse dynamics: the (pick, place) cells, two heads of NUM_CELLS."""
    return dd.IDConfig(**{"num_actions": HEADS * NUM_CELLS, **overrides})


def train_dd(out_dir: str, config: dd.DDTrainConfig = dd.DDTrainConfig(),
             model_config: dd.DDConfig | None = None, specs=SPECS, progress: bool = True):
    """diffplan.baselines.dd.train_dd on :func:`dd_trajectories` (batch a multiple of
    len(specs))."""
    return dd.train_dd(out_dir, functools.partial(dd_trajectories, specs=specs), GOAL_DIM,
                       config, model_config or dd_config(), data=specs_data(specs),
                       progress=progress)


def train_inverse_dynamics(out_dir: str, config: dd.DDTrainConfig = dd.DDTrainConfig(),
                           specs=SPECS, progress: bool = True):
    """diffplan.baselines.dd.train_inverse_dynamics on :func:`id_batch`."""
    return dd.train_inverse_dynamics(out_dir, functools.partial(id_batch, specs=specs), config,
                                     id_config(), FRAME_DIM, data=specs_data(specs),
                                     progress=progress)


def _frame_identity(frame):
    return frame


DD_POLICY_WORLD = PolicyWorld(goal_fn=goal_vector, goal_dim=GOAL_DIM, heads=HEADS,
                              action_fn=actions_of, frame_fn=_frame_identity,
                              observe=observe_blocks)
"""How the DD-style planner acts in the Kuka world: it observes block poses
(:func:`observe_blocks`), its inverse dynamics' two heads are the pick and place cells."""
POLICY_WORLDS = {"bc": POLICY_WORLD, "cql": Q_POLICY_WORLD, "dd": DD_POLICY_WORLD}
"""The world each Kuka baseline acts in (``diffplan.baselines.policies.load_policy``)."""
