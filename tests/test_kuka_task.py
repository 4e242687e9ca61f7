"""The Kuka world as a diffplan Task: condition channels, psi on hand-made plans, the training
expert's build order and targets, and the whole task under diffplan.rollout with an oracle
denoiser that in-paints the training expert's plan exactly (task + psi + primitive + physics end
to end, without training)."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffplan
import kuka_fixtures as kf
from diffplan.denoiser import LoadedDenoiser
from envs.kuka import env, expert, grid, physics, primitive, metrics, training
from envs.kuka.config import COLUMNS
from envs.kuka.episode import Episode
from envs.kuka import task as ktask

pytestmark = pytest.mark.filterwarnings(kf.MJX_CAST_WARNING)


def _flat_poses(block_xy):
    pos = np.concatenate([np.asarray(block_xy), np.full((4, 1), 0.03)], 1).astype(np.float32)
    return pos, np.tile(np.array([1.0, 0, 0, 0], np.float32), (4, 1))


def _signed(mask):
    return np.where(mask, 1.0, -1.0).astype(np.float32)


def _hand_plan(top, pick_block, place_block, path):
    return np.stack([_signed(path), _signed(top == place_block), _signed(top == pick_block)], -1)


def _state(column="rearrangement_single", seed=3, i=0):
    """State i at t = 0 (env.reset_batch: compiled once for every Kuka test)."""
    return jax.tree.map(lambda x: x[i], env.reset_batch(kf.episodes(column, seed)))


def test_condition_channels_are_the_view():
    state = _state()
    top, height = (np.asarray(a) for a in env.view(state))
    cond = np.asarray(ktask.KukaTask().condition(state))
    assert cond.shape == (24, 24, 2) and cond.dtype == np.float32
    # Channel 0: the colour word's token id (block i -> i + 1), 0 where no block is.
    np.testing.assert_array_equal(cond[..., 0], np.where(top >= 0, top + 1, 0))
    np.testing.assert_array_equal(cond[..., 1], height / 4)
    for b, cell in enumerate(np.asarray(grid.block_cells(physics.block_pos(state.data)))):
        assert cond[cell[0], cell[1], 0] == b + 1
    back_top, back_height = ktask.view_of_condition(jnp.asarray(cond))
    np.testing.assert_array_equal(back_top, top)
    np.testing.assert_array_equal(back_height, height)


@pytest.mark.parametrize("pick_block, place_block", [(2, 0), (1, 3), (3, 2)])
def test_psi_turns_a_hand_made_plan_into_its_pick_and_place(pick_block, place_block):
    state = _state()
    pos = np.asarray(physics.block_pos(state.data))
    top, _ = (np.asarray(a) for a in env.view(state))
    path = np.asarray(grid.path_map(pos[pick_block, :2], pos[place_block, :2]))
    plan = _hand_plan(top, pick_block, place_block, path)
    action = ktask.psi(state, jnp.asarray(plan))
    cells = np.asarray(action.cells)
    assert top[cells[0], cells[1]] == pick_block and top[cells[2], cells[3]] == place_block
    block, _, pick_xy, place_xy = env.resolve(state.data, cells)
    assert int(block) == pick_block
    np.testing.assert_allclose(place_xy, pos[place_block, :2], atol=1e-6)
    # The carry path follows the in-painted cells (here the expert's arc) from pick to place.
    wp = np.asarray(action.waypoints)
    assert wp.shape == (primitive.NUM_WAYPOINTS, 2)
    arc = np.asarray(grid.arc_points(pos[pick_block, :2], pos[place_block, :2], 200))
    gap = np.min(np.linalg.norm(wp[:, None] - arc[None], axis=-1), axis=1)
    assert gap.max() < grid.CELL, gap
    along = np.linalg.norm(wp - pos[pick_block, :2], axis=-1)
    assert along[0] < grid.CELL and np.linalg.norm(wp[-1] - pos[place_block, :2]) < grid.CELL
    assert (np.diff(along) > -0.25 * grid.CELL).all(), along  # moving away from the pick


def test_psi_orders_a_hand_drawn_path_and_falls_back_to_the_arc_when_broken():
    # An L-shaped path from (4, 4) down to (12, 4) and right to (12, 14).
    path = np.zeros((24, 24), bool)
    path[4:13, 4] = True
    path[12, 4:15] = True
    wp, ok = ktask.path_waypoints(jnp.asarray(_signed(path)), jnp.array([4, 4]),
                                  jnp.array([12, 14]), 12)
    wp = np.asarray(wp)
    assert bool(ok)
    cells = np.asarray(grid.xy_to_cell(jnp.asarray(wp)))
    np.testing.assert_array_equal(cells[0], [4, 4])
    np.testing.assert_array_equal(cells[-1], [12, 14])
    assert path[cells[:, 0], cells[:, 1]].all()
    steps = np.abs(np.diff(cells, axis=0)).sum(-1)
    assert (steps >= 1).all() and (steps <= 3).all(), cells  # in order along the L
    broken = path.copy()
    broken[12, 8] = False
    _, ok = ktask.path_waypoints(jnp.asarray(_signed(broken)), jnp.array([4, 4]),
                                 jnp.array([12, 14]), 12)
    assert not bool(ok)
    # psi then carries along the arc.
    state = _state()
    pos = np.asarray(physics.block_pos(state.data))
    top, _ = (np.asarray(a) for a in env.view(state))
    action = ktask.psi(state, jnp.asarray(_hand_plan(top, 0, 1, np.zeros((24, 24), bool))))
    np.testing.assert_allclose(action.waypoints,
                               grid.arc_points(pos[0, :2], pos[1, :2], 12), atol=1e-6)


def test_psi_picks_only_clear_blocks():
    # Green on red (exactly): red is covered; a plan that marks every cell as pick cannot
    # make psi grasp red from under green.
    episode = jax.tree.map(lambda x: x[0], kf.episodes("stacking_multi", 3))
    pos = np.asarray(expert.planned_poses(episode, 1))
    _, quat = _flat_poses(pos[:, :2])
    top, _ = grid.top_down_view(pos, quat)
    plan = np.full((24, 24, 3), 1.0, np.float32)
    lower, upper = np.asarray(episode.goal[0, 1]), np.asarray(episode.goal[0, 0])
    clear = np.asarray(ktask.clear_blocks(top, pos))
    assert not clear[lower] and clear[upper]
    pick, place, _ = ktask.decide(top, jnp.asarray(pos), jnp.asarray(plan))
    assert clear[int(pick)] and int(place) != int(pick)


def test_planner_goal_build_orders():
    def goal(constraints, tower):
        c = np.full((3, 2), -1, np.int32)
        c[:len(constraints)] = constraints
        ep = Episode(block_xy=np.zeros((4, 2), np.float32), constraints=c,
                           goal=c, tower=np.bool_(tower), max_steps=np.int32(6),
                           tokens=np.zeros(40, np.int32))
        return np.asarray(training.planner_goal(ep)).tolist()

    # Single-constraint tower: the instructed pair, then the others in colour order on top.
    assert goal([(2, 0)], True) == [[2, 0], [1, 2], [3, 1]]
    assert goal([(0, 3)], True) == [[0, 3], [1, 0], [2, 1]]
    # Independent relations: instruction order; a relation on another's top waits for it.
    assert goal([(0, 1), (2, 3)], False) == [[0, 1], [2, 3], [-1, -1]]
    assert goal([(3, 0), (0, 2)], False) == [[0, 2], [3, 0], [-1, -1]]
    assert goal([(1, 0)], False) == [[1, 0], [-1, -1], [-1, -1]]
    # A fully instructed tower, bottom up, in any instruction order.
    assert goal([(1, 2), (3, 1), (2, 0)], True) == [[2, 0], [1, 2], [3, 1]]


def test_the_denoiser_mixture_weights_the_eight_specs():
    """The default recipe trains on every spec of the even mixture, in its order, with the
    shares the docstring names; a Kuka batch of 32 holds whole shares."""
    from experiments.kuka import spec as kuka_spec

    specs = training.Recipe().specs
    assert specs == training.DENOISER_SPECS
    assert list(dict.fromkeys(specs)) == list(training.SPECS)
    shares = {(s.language, s.kind, s.multi): specs.count(s) for s in training.SPECS}
    assert shares == {("canonical", "stacking", False): 2,
                      ("canonical", "rearrangement", False): 1,
                      ("canonical", "stacking", True): 1, ("canonical", "rearrangement", True): 1,
                      ("paraphrased", "stacking", False): 2,
                      ("paraphrased", "rearrangement", False): 1,
                      ("paraphrased", "stacking", True): 3,
                      ("paraphrased", "rearrangement", True): 5}
    assert kuka_spec.TRAIN_BATCH % len(specs) == 0
    config = kuka_spec.train_config()
    assert config.num_train_timesteps >= kuka_spec.NUM_STEPS and config.timestep_power == 3.0


@pytest.mark.parametrize("spec", training.SPECS[:4], ids=lambda s: s.name)
def test_training_examples_are_the_experts_next_placement(spec):
    keys = jax.random.split(jax.random.PRNGKey(7), 16)
    x0, tokens, _, _ = jax.vmap(training.training_example, in_axes=(0, None, None))(
        keys, spec, 0.5)
    x0 = np.asarray(x0)
    assert x0.shape == (16, 24, 24, 5) and tokens.shape == (16, 40)
    assert set(np.unique(x0[..., 2:])) <= {-1.0, 1.0}
    for ex in x0:
        top, _ = (np.asarray(a) for a in ktask.view_of_condition(jnp.asarray(ex[..., :2])))
        pick_blocks = np.unique(top[ex[..., 4] > 0])
        place_blocks = np.unique(top[ex[..., 3] > 0])
        assert len(pick_blocks) == 1 and len(place_blocks) == 1
        assert pick_blocks[0] != place_blocks[0] and pick_blocks[0] >= 0
        # The path joins the two blocks.
        path = ex[..., 2] > 0
        assert (path & (top == pick_blocks[0])).any() and (path & (top == place_blocks[0])).any()


# ------------------------------------------------------------------ oracle end to end

@dataclasses.dataclass(frozen=True)
class OracleTask(ktask.KukaTask):
    """The Kuka task whose condition also carries the training expert's plan of the current
    physical state (channels 2-4, as training.plan_example draws it)."""

    num_cond_channels: int = 5

    def __post_init__(self):
        pass

    def condition(self, state):
        return training.plan_example(physics.block_pos(state.data),
                                     physics.block_quat(state.data), state.episode)


@dataclasses.dataclass(frozen=True)
class OracleApply:
    """A denoiser predicting x0 = the plan carried in the condition (so the sampler in-paints
    exactly the expert's plan)."""

    def __call__(self, params, x_t, t, tokens):
        return x_t[..., 2:5]


@pytest.fixture(scope="module")
def oracle_run():
    den = LoadedDenoiser(params={}, schedule=diffplan.cosine_schedule(100),
                         apply_fn=OracleApply(), prediction="x0", plan_shape=(24, 24, 3),
                         num_cond_channels=5)
    planner = diffplan.Planner(den, diffplan.PlannerConfig(mode="on_the_fly", num_steps=2))
    task = OracleTask()
    run = jax.jit(lambda p, k, e: diffplan.rollout(task, p, k, e))

    @__import__("functools").lru_cache(maxsize=None)
    def result(column, seed, language="canonical"):
        eps = kf.episodes(column, seed, language)
        out = run(planner, jax.random.split(jax.random.PRNGKey(seed), kf.BATCH), eps)
        return eps, jax.device_get(out)

    return task, result


@pytest.mark.parametrize("column", list(COLUMNS))
def test_oracle_plans_reach_the_experts_success(oracle_run, column):
    task, result = oracle_run
    eps, out = result(column, 21)
    final = out.final_state
    pos = np.asarray(jax.vmap(physics.block_pos)(final.data))
    held = np.asarray(jax.vmap(physics.held)(final.data))
    strict = [kf.numpy_on(pos[i], held[i], t, b) for i in range(kf.BATCH)
              for t, b in eps.constraints[i] if t >= 0]
    expert_final, _ = kf.expert_run(column, 21)
    expert_pos = np.asarray(jax.vmap(physics.block_pos)(expert_final.data))
    expert_strict = [kf.numpy_on(expert_pos[i], held[i], t, b) for i in range(kf.BATCH)
                     for t, b in eps.constraints[i] if t >= 0]
    assert np.mean(strict) >= np.mean(expert_strict) and np.mean(strict) == 1.0
    assert np.asarray(out.done).all()
    # One plan per placement (on-the-fly), as many placements as relations to build.
    needed = 3 if column.startswith("stacking") else (eps.constraints[:, :, 0] >= 0).sum(1)
    np.testing.assert_array_equal(out.steps, needed)
    np.testing.assert_array_equal(out.num_plans, out.steps)
    if column.startswith("stacking"):
        assert np.asarray(jax.vmap(metrics.single_tower)(pos, held)).all()
    # Positions: the flange over the block placed last.
    last = np.asarray(out.positions)[np.arange(kf.BATCH), out.steps]
    top, _ = jax.vmap(grid.top_down_view)(pos, np.asarray(jax.vmap(physics.block_quat)(
        final.data)), held)
    assert (np.asarray(top)[np.arange(kf.BATCH), last[:, 0], last[:, 1]] >= 0).all()


def test_oracle_follows_paraphrased_instructions(oracle_run):
    _, result = oracle_run
    eps, out = result("rearrangement_multi", 22, "paraphrased")
    pos = np.asarray(jax.vmap(physics.block_pos)(out.final_state.data))
    held = np.asarray(jax.vmap(physics.held)(out.final_state.data))
    assert all(kf.numpy_on(pos[i], held[i], t, b) for i in range(kf.BATCH)
               for t, b in eps.constraints[i] if t >= 0)


def test_replan_triggers():
    task = ktask.KukaTask()
    state = _state("rearrangement_single", 3)
    zeros = jnp.zeros((24, 24, 3))
    assert not bool(task.at_goal_estimate(state, zeros))
    cond = task.condition(state)
    assert not bool(task.new_information(cond, cond))
    pos = np.array(physics.block_pos(state.data))
    pos[1, :2] += 0.1
    moved = state.replace(data=physics.set_blocks(state.data, pos,
                                                  physics.block_quat(state.data)))
    assert bool(task.new_information(cond, task.condition(moved)))
    # The flange's cell in the goal estimate: the plan's placement is done.
    cell = np.asarray(task.position(state))
    plan = np.full((24, 24, 3), -1.0, np.float32)
    plan[cell[0], cell[1], ktask.GOAL] = 1.0
    assert bool(task.at_goal_estimate(state, jnp.asarray(plan)))
    with pytest.raises(ValueError):
        ktask.KukaTask(num_cond_channels=3)
    assert hash(task) == hash(ktask.KukaTask())


def test_block_scores_prefer_the_block_the_map_covers():
    """A 9-cell block under a goal blob (0.8) beats a 2-cell sliver of a covered block the blob
    spilled onto (1.0): scores are sums, the best-matching +1/-1 target map; invisible blocks
    score -inf."""
    from envs.kuka.task import block_scores

    top = np.full((24, 24), -1)
    top[5:8, 5:8] = 1          # block 1: clear, 9 visible cells
    top[8, 5:7] = 2            # block 2: a sliver of 2 visible cells
    values = np.full((24, 24), -1.0)
    values[5:8, 5:8] = 0.8
    values[8, 5:7] = 1.0
    scores = np.asarray(block_scores(top, jnp.asarray(values)))
    assert np.argmax(scores) == 1
    assert scores[1] == pytest.approx(7.2) and scores[2] == pytest.approx(2.0)
    assert np.isneginf(scores[0]) and np.isneginf(scores[3])
