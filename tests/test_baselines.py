"""The world-agnostic baselines (diffplan.baselines) on a toy world defined here, a 1-D corridor,
so that BC, CQL, the DD-style planner, their loading and the policy rollout are shown to need
no grid world: the conv net's parameter tree, BC and CQL learning the corridor through their
training functions and acting through policy_rollout, the epsilon-greedy collector, CQL's
conservative term on a tabular MDP, the DD-style batches, and the DD-style policy acting with
an oracle denoiser and a trained inverse dynamics. This module imports nothing from envs/ or
experiments/ (the grid world's baselines: tests/test_gridworld_baselines.py)."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from diffplan.baselines import bc, cql, dd, nets
from diffplan.baselines.policies import PolicyWorld, export_params, load_policy
from diffplan.baselines.rollout import policy_rollout
from diffplan.train import TrainState

# --------------------------------------------------------------------- the toy world

N = 6
"""Cells of the corridor. The agent walks left (action 0) or right (1) towards the goal cell
that the one-token instruction names; the condition is the agent's cell one-hot (1, N, 1)."""
MAX_STEPS = 8
LEFT, RIGHT = 0, 1


def corridor_goal(tokens):
    """The corridor's goal vector: one-hot (B, N) of the instruction's goal cell."""
    return jax.nn.one_hot(jnp.asarray(tokens)[..., 0], N)


def corridor_condition(agent):
    return jax.nn.one_hot(agent, N)[None, :, None]


def corridor_expert(agent, goal):
    return jnp.where(goal > agent, RIGHT, LEFT).astype(jnp.int32)


def corridor_frame(condition):
    return condition[0, :, 0]


def corridor_plan(trajectory, condition):
    return jnp.where(jnp.any(trajectory > 0.5, -1), 1.0, -1.0).reshape(condition.shape[:2])[
        ..., None]


def all_episodes():
    """Every (start, goal) pair with start != goal: 30 episodes."""
    pairs = [(s, g) for s in range(N) for g in range(N) if s != g]
    return {"start": jnp.array([p[0] for p in pairs], jnp.int32),
            "goal": jnp.array([p[1] for p in pairs], jnp.int32)}


def random_episodes(key, n):
    k1, k2 = jax.random.split(key)
    start = jax.random.randint(k1, (n,), 0, N)
    goal = (start + jax.random.randint(k2, (n,), 1, N)) % N
    return {"start": start, "goal": goal}


@dataclasses.dataclass(frozen=True)
class Corridor:
    """diffplan.task.Task of the corridor (what policy_rollout uses) and
    diffplan.baselines.cql.Collector (what the CQL buffer is collected with)."""

    height: int = 1
    width: int = N
    num_cond_channels: int = 1
    num_gen_channels: int = 1
    max_steps: int = MAX_STEPS
    num_actions: int = 2

    def episodes(self, key, n):
        return random_episodes(key, n)

    def reset(self, episode):
        return {"agent": episode["start"], "goal": episode["goal"], "t": jnp.int32(0),
                "done": jnp.array(False), "success": jnp.array(False)}

    def tokens(self, episode):
        return episode["goal"][None]

    instruction = tokens

    def condition(self, state):
        return corridor_condition(state["agent"])

    def observe(self, state):
        return state["agent"].astype(jnp.int8)

    def step(self, state, action):
        agent = jnp.clip(state["agent"] + jnp.where(action == RIGHT, 1, -1), 0, N - 1)
        success = agent == state["goal"]
        new = {"agent": agent, "goal": state["goal"], "t": state["t"] + 1, "success": success,
               "done": success | (state["t"] + 1 >= self.max_steps)}
        return jax.tree.map(lambda a, b: jnp.where(state["done"], a, b), state, new)

    def expert_action(self, state):
        return corridor_expert(state["agent"], state["goal"])

    def reward(self, state):
        return -jnp.abs(state["goal"] - state["agent"]).astype(jnp.float32) / N

    def terminal(self, state):
        return state["success"]

    def done(self, state):
        return state["done"]

    def position(self, state):
        return jnp.stack([jnp.int32(0), state["agent"]])


CORRIDOR = Corridor()
WORLD = PolicyWorld(goal_fn=corridor_goal, goal_dim=N, frame_fn=corridor_frame,
                    plan_fn=corridor_plan, plan_channels=1)
SHAPES = {"condition": (1, 1, N, 1), "goal": (1, N)}
SMALL_NET = nets.ConvNetConfig(channels=4, hidden=16, num_outputs=2)


def corridor_bc_batch(key, batch_size):
    """(conditions (B, 1, N, 1), goal vectors (B, N), expert actions (B,))."""
    eps = random_episodes(key, batch_size)
    return (jax.vmap(corridor_condition)(eps["start"]), jax.nn.one_hot(eps["goal"], N),
            corridor_expert(eps["start"], eps["goal"]))


def q_inputs(obs, instruction):
    return jax.vmap(corridor_condition)(obs.astype(jnp.int32)), corridor_goal(instruction)


def run(policy, params, calls_per_move=0, plan_channels=None):
    """policy_rollout of every corridor episode (numpy)."""
    episodes = all_episodes()
    keys = jax.random.split(jax.random.PRNGKey(0), len(episodes["start"]))
    fn = jax.jit(lambda p, k, e: policy_rollout(CORRIDOR, policy, p, k, e,
                                                calls_per_move=calls_per_move,
                                                plan_channels=plan_channels))
    return episodes, jax.device_get(fn(params, keys, episodes))


def assert_solves_every_episode(episodes, out):
    distance = np.abs(np.asarray(episodes["goal"]) - np.asarray(episodes["start"]))
    assert out.final_state["success"].all()
    np.testing.assert_array_equal(out.steps, distance)  # shortest: no step away from the goal


# ------------------------------------------------------------------------ the network

def test_goal_conv_net_takes_the_goal_vector_before_its_last_dense_layer():
    params = nets.init_net(nets.GoalConvNet(nets.ConvNetConfig()), jax.random.PRNGKey(0),
                           {"condition": (1, 16, 16, 5), "goal": (1, 38)})
    shapes = jax.tree.map(lambda x: x.shape, params)
    assert shapes == {"conv1": {"kernel": (3, 3, 5, 16), "bias": (16,)},
                      "conv2": {"kernel": (3, 3, 16, 16), "bias": (16,)},
                      "dense1": {"kernel": (16 * 16 * 16, 40), "bias": (40,)},
                      "dense2": {"kernel": (40 + 38, 40), "bias": (40,)},
                      "head": {"kernel": (40, 4), "bias": (4,)}}


def test_greedy_act_reads_the_goal_through_the_world_function():
    model = nets.GoalConvNet(SMALL_NET)
    act = nets.greedy_act(model, corridor_goal)
    assert act == nets.greedy_act(model, corridor_goal)  # hashable: one compilation
    params = nets.init_net(model, jax.random.PRNGKey(1), SHAPES)
    conditions = jax.vmap(corridor_condition)(jnp.arange(N))
    tokens = jnp.full((N, 1), 2)
    expected = jnp.argmax(model.apply({"params": params}, conditions, jax.nn.one_hot(
        jnp.full((N,), 2), N)), -1)
    np.testing.assert_array_equal(act(params, conditions, tokens, None), expected)


# --------------------------------------------------------------------------------- BC

def test_bc_trains_on_a_world_batch_fn_and_solves_the_corridor(tmp_path):
    cfg = bc.BCTrainConfig(seed=1, steps=150, batch_size=64, lr=1e-2, checkpoint_every=150,
                           log_every=50)
    result = bc.train_bc(str(tmp_path / "bc"), corridor_bc_batch, SHAPES, cfg, SMALL_NET,
                         data={"world": "corridor"}, progress=False)
    assert result.last_record["accuracy"] > 0.95
    export_params(str(tmp_path / "bc"), str(tmp_path / "ship" / "bc"))
    policy = load_policy("bc", str(tmp_path / "ship" / "bc"), WORLD)
    jax.tree.map(np.testing.assert_array_equal, policy.params,
                 jax.device_get(result.state.params))
    # The checkpoint records the goal vector's shape: the registry's checked load works too.
    from diffplan.checkpoint import load_params_for_eval
    _, meta = load_params_for_eval(str(tmp_path / "ship" / "bc"), SMALL_NET)
    assert meta["input_shapes"] == {"condition": [1, 1, N, 1], "goal": [1, N]}
    assert_solves_every_episode(*run(policy.act_fn, policy.params))


def test_bc_refuses_to_resume_on_other_data(tmp_path):
    from diffplan.train import ConfigMismatchError

    cfg = bc.BCTrainConfig(steps=2, batch_size=8, checkpoint_every=2, log_every=1)
    bc.train_bc(str(tmp_path), corridor_bc_batch, SHAPES, cfg, SMALL_NET,
                data={"world": "corridor"}, progress=False)
    with pytest.raises(ConfigMismatchError):
        bc.train_bc(str(tmp_path), corridor_bc_batch, SHAPES, dataclasses.replace(cfg, steps=4),
                    SMALL_NET, data={"world": "other"}, progress=False)


# -------------------------------------------------------------------------------- CQL

def _tabular_cql(alpha: float, steps: int = 400):
    """Two states; the data only ever takes action 0 in s0 (reward -1, to s1) and action 1
    in s1 (reward 0, terminal). Q is a table initialised at 0."""
    buffer = {"obs": jnp.array([0, 1]), "next_obs": jnp.array([1, 1]),
              "action": jnp.array([0, 1]), "reward": jnp.array([-1.0, 0.0]),
              "terminal": jnp.array([False, True])}
    q_fn = lambda params, obs: params["q"][obs]  # noqa: E731
    params = {"q": jnp.zeros((2, 4))}
    optimizer = optax.adam(0.05)
    state = TrainState(params=params, ema_params=params, opt_state=optimizer.init(params),
                       step=jnp.zeros((), jnp.int32))
    step = jax.jit(cql.make_cql_step(q_fn, optimizer, batch_size=8, gamma=0.99, alpha=alpha,
                                     tau=0.1))
    for i in range(steps):
        state, _ = step(state, jax.random.PRNGKey(i), buffer)
    return np.asarray(state.params["q"])


def test_cql_pushes_down_the_q_values_of_actions_absent_from_the_data():
    seen = np.zeros((2, 4), bool)
    seen[0, 0] = seen[1, 1] = True
    q_dqn, q_cql = _tabular_cql(alpha=0.0), _tabular_cql(alpha=1.0)
    # Double DQN alone never touches the unseen actions: they stay at 0, above the data
    # action of s0 (worth about -1), so the greedy policy leaves the data.
    np.testing.assert_allclose(q_dqn[~seen], 0.0)
    assert q_dqn[0, 0] == pytest.approx(-1.0, abs=0.05)
    assert q_dqn[0].argmax() != 0
    # With the conservative term they are pushed below the data actions.
    assert np.all(q_cql[~seen] < q_dqn[~seen] - 0.5)
    for s, a in ((0, 0), (1, 1)):
        others = np.delete(q_cql[s], a)
        assert np.all(others < q_cql[s, a] - 0.5), q_cql
    assert q_cql[0].argmax() == 0 and q_cql[1].argmax() == 1


def test_epsilon_is_annealed_linearly_then_held():
    eps = np.asarray(cql.epsilon_at(jnp.array([0, 5000, 10000, 20000])))
    np.testing.assert_allclose(eps, [1.0, 0.505, 0.01, 0.01], rtol=1e-6)


def test_the_collector_follows_the_behaviour_of_any_world():
    """Two worlds (the corridor twice, counts 3 : 1) of 16 collectors: each world's share of
    the buffer, epsilon annealed over each world's own frames, expert moves late, rewards of
    the state reached, terminal rows, fresh episodes after the end."""
    slow = dataclasses.replace(CORRIDOR, max_steps=4)
    cfg = cql.CQLTrainConfig(buffer_size=1600, collectors=16, epsilon_frames=160)
    buffer = jax.device_get(cql.collect_buffer(jax.random.PRNGKey(3),
                                               ((CORRIDOR, 3), (slow, 1)), cfg))
    assert buffer["action"].shape == (1600,) and buffer["action"].dtype == np.int8
    agent = buffer["obs"].astype(int)
    nxt = buffer["next_obs"].astype(int)
    goal = buffer["instruction"][:, 0].astype(int)
    np.testing.assert_array_equal(nxt, np.clip(agent + np.where(buffer["action"] == 1, 1, -1),
                                               0, N - 1))
    np.testing.assert_allclose(buffer["reward"], -np.abs(goal - nxt) / N)
    np.testing.assert_array_equal(buffer["terminal"], nxt == goal)
    expert = np.where(goal > agent, 1, 0)
    first = 12 * 100  # world 0: 12 collectors x 100 moves, then world 1: 4 x 100
    for lo, hi, collectors in ((0, first, 12), (first, 1600, 4)):
        follows = buffer["action"][lo:hi] == expert[lo:hi]
        late = np.arange(hi - lo) >= 160 + collectors  # epsilon 0.01 after 160 frames
        assert follows[late].mean() > 0.97
        assert follows[:collectors * 8].mean() < 0.8  # the first frames: epsilon near 1
    assert buffer["terminal"].sum() > 100


def test_cql_trains_on_collected_transitions_and_solves_the_corridor(tmp_path):
    cfg = cql.CQLTrainConfig(seed=2, steps=400, batch_size=64, lr=1e-2, gamma=0.9, tau=0.05,
                             buffer_size=2048, collectors=32, epsilon_frames=512,
                             checkpoint_every=400, log_every=100)
    cql.train_cql(str(tmp_path / "cql"), ((CORRIDOR, 1),), q_inputs, SHAPES, cfg, SMALL_NET,
                  data={"world": "corridor"}, progress=False)
    export_params(str(tmp_path / "cql"), str(tmp_path / "ship" / "cql"))
    policy = load_policy("cql", str(tmp_path / "ship" / "cql"), WORLD)
    assert_solves_every_episode(*run(policy.act_fn, policy.params))


# ---------------------------------------------------------------------------- DD-style

HORIZON = 4
TOY_DD = dd.DDConfig(horizon=HORIZON, cells=N, widths=(8, 16), embed_dim=8, groups=4,
                     head_width=16)


def corridor_trajectory(start, goal):
    """float32 (N, HORIZON): the expert's frames from start (the end repeated)."""
    step = jnp.where(goal > start, 1, -1)
    cells = start + step * jnp.arange(HORIZON)
    cells = jnp.where(step * (cells - goal) > 0, goal, cells)
    return jax.nn.one_hot(cells, N).T


def corridor_trajectories(key, batch_size):
    eps = random_episodes(key, batch_size)
    return (jax.vmap(corridor_trajectory)(eps["start"], eps["goal"]),
            jax.nn.one_hot(eps["goal"], N))


def corridor_id_batch(key, batch_size):
    """(frames (B, N), next frames (B, N), expert actions (B,))."""
    eps = random_episodes(key, batch_size)
    traj = jax.vmap(corridor_trajectory)(eps["start"], eps["goal"])
    return traj[..., 0], traj[..., 1], corridor_expert(eps["start"], eps["goal"])


def test_dd_batches_drop_the_goal_and_weigh_the_changes():
    key = jax.random.PRNGKey(0)
    kept = dd.DDBatchFn(corridor_trajectories, p_uncond=0.0, change_weight=9.0)(key, 32)
    dropped = dd.DDBatchFn(corridor_trajectories, p_uncond=1.0, change_weight=9.0)(key, 32)
    traj, goals = corridor_trajectories(jax.random.split(key)[0], 32)
    np.testing.assert_array_equal(kept.x0, traj[:, None])
    np.testing.assert_array_equal(kept.tokens, goals)
    assert not np.asarray(dropped.tokens).any()
    changed = np.abs(np.asarray(traj[..., 1:] - traj[..., :1])) > 1e-6
    np.testing.assert_array_equal(np.asarray(kept.loss_mask)[:, 0], 1 + 9 * changed)


@dataclasses.dataclass(frozen=True)
class OracleApply:
    """A denoiser's apply_fn that predicts (x0) the expert's frames 1.. from frame 0 and the
    goal vector: with it the DD-style policy must take the expert's every move."""

    def __call__(self, params, x_t, t, goal):
        start = jnp.argmax(x_t[:, 0, :, 0], -1)
        traj = jax.vmap(corridor_trajectory)(start, jnp.argmax(goal, -1))
        return traj[:, None, :, 1:]


def test_dd_policy_acts_with_the_world_functions(tmp_path):
    """The inverse dynamics trained on the corridor's consecutive frames, the oracle as the
    diffusion model: every episode solved by shortest paths, 2 denoiser calls per move, the
    first plan the path's cells."""
    id_config = dd.IDConfig(hidden=(32,), num_actions=2)
    cfg = dd.DDTrainConfig(seed=0, id_steps=200, id_batch_size=64, id_lr=1e-2,
                           checkpoint_every=200, log_every=100)
    result = dd.train_inverse_dynamics(str(tmp_path / "id"), corridor_id_batch, cfg, id_config,
                                       cells=N, progress=False)
    assert result.last_record["accuracy"] > 0.95
    den = dd.denoiser(None, TOY_DD, "x0", 100)
    den = den.replace(apply_fn=OracleApply())
    policy = dd.DDPolicy(TOY_DD, corridor_goal, corridor_frame, corridor_plan,
                         id_config=id_config, num_steps=2)
    params = {"denoiser": den, "inverse_dynamics": result.state.params}
    episodes, out = run(policy, params, policy.calls_per_move, plan_channels=1)
    assert_solves_every_episode(episodes, out)
    np.testing.assert_array_equal(out.denoiser_calls, 2 * out.steps)
    start, goal = np.asarray(episodes["start"]), np.asarray(episodes["goal"])
    for i in range(len(start)):
        lo, hi = sorted((start[i], start[i] + np.sign(goal[i] - start[i]) * (HORIZON - 1)))
        on = (np.arange(N) >= max(lo, min(start[i], goal[i]))) & (
            np.arange(N) <= min(hi, max(start[i], goal[i])))
        np.testing.assert_array_equal(out.first_plan[i, 0, :, 0], np.where(on, 1.0, -1.0))


def test_dd_trains_on_world_trajectories_and_loads_with_the_world_goal(tmp_path):
    """train_dd + train_inverse_dynamics on the corridor, shipped, loaded through load_policy
    (shapes checked against the world's goal vector), one act call."""
    cfg = dd.DDTrainConfig(steps=2, batch_size=8, checkpoint_every=2, log_every=1, id_steps=2,
                           id_batch_size=8)
    id_config = dd.IDConfig(hidden=(8,), num_actions=2)
    dd.train_dd(str(tmp_path / "dd" / "diffusion"), corridor_trajectories, N, cfg, TOY_DD,
                data={"world": "corridor"}, progress=False)
    dd.train_inverse_dynamics(str(tmp_path / "dd" / "inverse_dynamics"), corridor_id_batch, cfg,
                              id_config, cells=N, progress=False)
    for part in ("diffusion", "inverse_dynamics"):
        export_params(str(tmp_path / "dd" / part), str(tmp_path / "ship" / "dd" / part),
                      ema=part == "diffusion")
    policy = load_policy("dd", str(tmp_path / "ship" / "dd"), WORLD, dd_num_steps=1)
    assert policy.plan_channels == 1 and policy.calls_per_move == 1
    conditions = jax.vmap(corridor_condition)(jnp.array([0, 5]))
    moves, plans = policy.act_fn(policy.params, conditions, jnp.array([[5], [0]]),
                                 jax.random.split(jax.random.PRNGKey(0), 2))
    assert moves.shape == (2,) and plans.shape == (2, 1, N, 1)
    with pytest.raises(ValueError, match="does not fit"):
        load_policy("dd", str(tmp_path / "ship" / "dd"), dataclasses.replace(WORLD, goal_dim=3))
    with pytest.raises(ValueError, match="frame_fn"):
        load_policy("dd", str(tmp_path / "ship" / "dd"), PolicyWorld(corridor_goal, N))


def test_loading_never_imports_the_class_a_checkpoint_names(tmp_path, monkeypatch):
    """A checkpoint whose metadata names a module that writes a file when imported: the
    policy loads (its network is built from this package's config classes), the file never
    appears."""
    from diffplan import checkpoint as ckpt

    marker = tmp_path / "imported"
    (tmp_path / "h2_planted.py").write_text(f"open({str(marker)!r}, 'w').write('ran')\n"
                                            "class Net:\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    params = nets.init_net(nets.GoalConvNet(SMALL_NET), jax.random.PRNGKey(0), SHAPES)
    meta = {"model_class": "h2_planted:Net", "model_config_class": "h2_planted:Net",
            "model_config": SMALL_NET.to_dict(), "input_shapes": SHAPES}
    ckpt.save_checkpoint(str(tmp_path / "bc"), 1, params, meta)
    policy = load_policy("bc", str(tmp_path / "bc"), WORLD)
    jax.tree.map(np.testing.assert_array_equal, policy.params, jax.device_get(params))
    assert not marker.exists()
