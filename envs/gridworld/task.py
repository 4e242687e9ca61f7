"""The grid world as a planner task: condition channels and psi.

Planning tensor of the grid world (H x W x (C + G), C = 5, G = 3):
  channel 0  cell token id (float-valued integer; see env.Observation.cells),
  channels 1-4  obstacle seen, agent, visited, visible (0/1),
  channel 5  path: +1 on the cells of the plan, -1 elsewhere (a denoiser trained with
             ``Recipe.later_leg_value`` v < 1 marks the cells only the plan's leg after the
             reference passes with v: the search psi reads any value > 0 as path, the follow
             psi any value above its mark (:data:`FOLLOW_MARK`), and both prefer the
             stronger mark),
  channel 6  goal estimate: +1 on the believed target cell, -1 elsewhere,
  channel 7  sub-goal: +1 on the cell the instruction asks for next (in P-MO2G the reference
             until the agent has stood on it, then the target; the target in the other
             settings), -1 elsewhere.
Models trained before the sub-goal channel existed have G = 2 (``GridTask(num_gen_channels=2)``).

psi (the inverse dynamics, Sec. 3.3 of the paper): from the agent's cell, the first move of the
cheapest path to the cell the plan heads for (:func:`goal_estimate`: the sub-goal channel's
argmax among cells neither visited nor known to be obstacles; with G = 2 the goal channel's
argmax) over the cells not known to be obstacles (unseen cells are assumed free), where entering
a cell costs ``1 + path_weight * (1 - p)`` with p in [0, 1] the plan's path value of that cell.
Cells the plan marks as path are therefore preferred, and the agent follows the plan's route
rather than the straight line to the goal. While the sub-goal is not the goal estimate, entering
the goal estimate's cell costs ``AVOID_GOAL_COST`` more, so that the agent does not end the
episode on the target before it has done what the instruction asks first. A Dijkstra-style field
computed by Bellman-Ford relaxation in JAX. psi never moves into a known obstacle or off the
grid; as the field of view is at least one cell around the agent, it never collides.

``GridTask(psi_kind="follow")`` is the paper's psi instead (:func:`psi_follow`): the move onto
the neighbouring legal cell (on the grid, not a known obstacle) that the plan marks most
strongly as path (path value above :data:`FOLLOW_MARK`, -0.8; cells already visited only when no
other neighbour is marked), with no search over the map. Where the drawn path forks at the
agent's cell (the leg after the reference often passes beside it), the marks are read forward
along each marked branch with this same rule (:func:`_branch_moves`), and the strongest branch
that leads to the cell the plan heads for is taken. Where no neighbour is marked the rollout
plans again once (``diffplan.rollouts.move``), and if the second plan marks none either, the
agent steps greedily toward the cell the plan heads for (the legal neighbour nearest to it in
moves, ignoring obstacles: no search); such fallback moves are counted. As in the search, while
the sub-goal is not the goal estimate the goal estimate's cell is not a candidate.

The training examples of the denoiser (what each channel's target is) live in
``envs.gridworld.training``.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from envs.gridworld import bfs, env
from envs.gridworld.config import GridConfig
from envs.gridworld.episode import OBSTACLE_CELL, Episode

NUM_COND_CHANNELS = 1 + env.NUM_FEATURES
NUM_GEN_CHANNELS = 3
AGENT_CHANNEL = 2
"""The condition channel marking the agent's cell (the "agent" feature)."""
PATH_CHANNEL, GOAL_CHANNEL, SUBGOAL_CHANNEL = (NUM_COND_CHANNELS, NUM_COND_CHANNELS + 1,
                                               NUM_COND_CHANNELS + 2)
TEXT_INPUTS = ("tokens", "features")
"""What a GridTask hands the planner of an episode's instruction (``GridTask.text``)."""
AVOID_GOAL_COST = 50.0
"""Extra cost of entering the goal estimate's cell while heading for a different sub-goal."""
FOLLOW_MARK = -0.8
"""psi_follow reads a cell as marked when its path value is above this (the channel spans
[-1, 1], -1 no path). Not the middle of the channel: a drawn path often fades where it has a
gap, and a low mark follows the faint marks on. Chosen on validation seed 1000 over 0, -0.5,
-0.8 and -0.9 (docs/results.md); ``GridTask(follow_mark=...)`` and ``--follow-mark`` set it."""


def check_follow_mark(mark: float, name: str = "follow_mark") -> None:
    """Raises ValueError unless mark is a path value psi_follow can read, in [-1, 1) (NaN
    refused); name: what the message calls it (a flag, a key)."""
    if not -1 <= mark < 1:
        raise ValueError(f"{name} must be in [-1, 1), got {mark}")


def condition_from_observation(obs: env.Observation):
    """float32 (H, W, C) condition channels from an observation."""
    return jnp.concatenate([obs.cells[..., None].astype(jnp.float32),
                            obs.features.astype(jnp.float32)], axis=-1)


def goal_cell(plan, excluded=None):
    """int32 (2,): the argmax cell of the plan's goal channel (plan float32 (H, W, G)), among
    cells not in ``excluded`` (bool (H, W), e.g. known obstacles)."""
    goal = plan[..., 1]
    return _argmax_cell(goal, jnp.zeros(goal.shape, bool) if excluded is None else excluded)


def path_end_cell(plan, agent, excluded=None):
    """int32 (2,): where the plan's path leads from the agent: among the path cells (value > 0,
    not in ``excluded``) connected to the agent's cell through such cells (4-neighbours), the
    one farthest along them (BFS distance); the agent's cell if none. The goal of a model
    trained without a goal channel (the paper's ablations without g). Stray path cells not
    connected to the agent are ignored; psi excludes the visited cells too, so that an agent
    half way along its path heads on, not back to where it came from."""
    size = plan.shape[1]
    on_path = plan[..., 0] > 0
    if excluded is not None:
        on_path = on_path & ~excluded
    at_agent = env._cell_mask(agent, size)
    along = bfs.bfs_distance(on_path | at_agent, agent)  # -1 where not connected
    score = jnp.where(on_path, along, -1).ravel()
    flat = jnp.argmax(score)
    cell = jnp.stack([flat // size, flat % size]).astype(jnp.int32)
    return jnp.where(score[flat] >= 0, cell, agent.astype(jnp.int32))


UNSEEN_CELL = -2
"""What :func:`known_grid` holds where the agent has not seen (episode cells are 0 empty,
-1 obstacle, k >= 1 an object)."""


def known_grid(state: env.State):
    """int8 (H, W): the world as the agent knows it, the grid where it has seen a cell and
    :data:`UNSEEN_CELL` elsewhere. The only way the agent's side of the task (psi, the re-plan
    triggers, the ranking of plans) reads the grid, so that nothing it does depends on a cell
    it has not seen (docs/DESIGN.md, "What the agent acts on")."""
    return jnp.where(state.seen, state.grid, jnp.int8(UNSEEN_CELL)).astype(jnp.int8)


def known_obstacles(state: env.State):
    """bool (H, W): the cells the agent has seen to be obstacles."""
    return known_grid(state) == OBSTACLE_CELL


def goal_estimate(state: env.State, plan, use_goal_channel: bool = True):
    """int32 (2,): the cell psi heads for (plan float32 (H, W, G)).

    G >= 3: the sub-goal channel's argmax among cells neither known to be obstacles nor
    visited (the agent never heads back to where it has been; the target is never visited
    while the episode runs). G = 2: the goal channel's argmax off known obstacles.
    use_goal_channel=False (models trained without goal channels): the end of the unvisited
    path connected to the agent."""
    known_obstacle = known_obstacles(state)
    if not use_goal_channel:
        return path_end_cell(plan, state.agent, known_obstacle | state.visited)
    if plan.shape[-1] >= 3:
        return _argmax_cell(plan[..., 2], known_obstacle | state.visited)
    return goal_cell(plan, known_obstacle)


def plan_refuted(state: env.State, plan, use_goal_channel: bool = True):
    """bool (): what the agent has seen contradicts the plan (plan float32 (H, W, G)). Read
    from the seen cells and the plan alone, never from which object the instruction names
    (the agent does not know it: only the denoiser reads the instruction):
    - the cell the plan heads for (:func:`goal_estimate`) has been seen and holds no object
      (an instruction only ever sends the agent to an object), or
    - with a goal channel, the cell of the plan's goal estimate (its argmax off known
      obstacles) has been seen and holds no object: the guess of the goal is disproved, or
    - a cell the plan marks as path (value > 0) has been seen to be an obstacle: the route
      was drawn through what is now known to be blocked, or
    - the plan marks no cell it may still head for (its sub-goal cell became a known obstacle
      or was visited).
    Reaching the cell the plan heads for without the episode ending asks for a new plan too
    (``task.at_goal_estimate``, which every trigger adds)."""
    known = known_grid(state)
    seen_no_object = state.seen & (known <= 0)
    heading = goal_estimate(state, plan, use_goal_channel)
    wrong = seen_no_object[heading[0], heading[1]]
    if use_goal_channel:
        goal = goal_cell(plan, known == OBSTACLE_CELL)
        wrong = wrong | seen_no_object[goal[0], goal[1]]
    wrong = wrong | jnp.any((plan[..., 0] > 0) & (known == OBSTACLE_CELL))
    if use_goal_channel and plan.shape[-1] >= 3:
        wrong = wrong | (plan[heading[0], heading[1], 2] <= 0)
    return wrong


REFUTED_PLAN_COST = 1e4
""":func:`plan_cost` of a plan already refuted (more than any path on a 16 x 16 grid)."""


def plan_cost(state: env.State, plan, use_goal_channel: bool = True):
    """float32 (): moves from the agent to the cell the plan heads for (:func:`goal_estimate`)
    over cells not known to be obstacles (unseen cells count as free), plus REFUTED_PLAN_COST
    if what has been seen already refutes the plan (:func:`plan_refuted`). Ranks several drawn
    plans (``PlannerConfig.samples``): of several guesses, the nearest that what the agent has
    seen still allows."""
    passable = ~known_obstacles(state)
    heading = goal_estimate(state, plan, use_goal_channel)
    moves = bfs.cost_to_go(passable, heading)[state.agent[0], state.agent[1]]
    refuted = plan_refuted(state, plan, use_goal_channel)
    return moves.astype(jnp.float32) + REFUTED_PLAN_COST * refuted


PSI_KINDS = ("search", "follow")
"""``GridTask.psi_kind``: Dijkstra toward the sub-goal over path-cheapened cells (:func:`psi`),
or the paper's neighbour-following psi (:func:`psi_follow`)."""


def _follow_targets(state: env.State, plan, use_goal_channel: bool = True):
    """(heading int32 (2,) the cell the plan heads for, avoid int32 (2,) the goal estimate's
    cell while the sub-goal is elsewhere ((-1, -1) otherwise, never a neighbour), or None
    without a sub-goal channel): what psi_follow steers by; they change only as cells
    are seen or the heading is reached."""
    heading = goal_estimate(state, plan, use_goal_channel)
    if not (use_goal_channel and plan.shape[-1] >= 3):
        return heading, None
    goal = goal_cell(plan, known_obstacles(state))
    return heading, jnp.where(jnp.any(goal != heading), goal, -1).astype(jnp.int32)


def _follow_candidates(state: env.State, plan, use_goal_channel: bool = True, targets=None,
                       mark: float = FOLLOW_MARK):
    """What psi_follow weighs: (cells int32 (4, 2) the neighbours N, E, S, W, legal bool (4,)
    on the grid and not known obstacles (nor the goal estimate's cell while the sub-goal is
    elsewhere), score float32 (4,) the path value of the candidates (-inf elsewhere): the
    marked (path > mark) unvisited neighbours, or the marked visited ones when there are none,
    heading int32 (2,) the cell the plan heads for, ahead bool () some unvisited neighbour is
    marked). targets: :func:`_follow_targets` if already known. mark: a cell whose path value
    is above it is marked (:data:`FOLLOW_MARK`)."""
    h, w = state.seen.shape
    cells, inside = bfs.neighbours(state.agent, (h, w))
    r = jnp.clip(cells[:, 0], 0, h - 1)
    c = jnp.clip(cells[:, 1], 0, w - 1)
    known_obstacle = known_obstacles(state)
    legal = inside & ~known_obstacle[r, c]
    heading, avoid_cell = _follow_targets(state, plan, use_goal_channel) if targets is None \
        else targets
    if avoid_cell is not None:
        legal = legal & ~jnp.all(cells == avoid_cell, axis=-1)
    path = plan[..., 0][r, c]
    marked = legal & (path > mark)
    fresh = marked & ~state.visited[r, c]
    use = jnp.where(fresh.any(), fresh, marked)
    return cells, legal, jnp.where(use, path, -jnp.inf), heading, fresh.any()


def unfollowable(state: env.State, plan, use_goal_channel: bool = True,
                 mark: float = FOLLOW_MARK):
    """bool (): the plan marks no legal neighbour of the agent as path (psi_follow falls
    back)."""
    _, _, score, _, _ = _follow_candidates(state, plan, use_goal_channel, mark=mark)
    return ~jnp.any(jnp.isfinite(score))


def _replay_moves(state: env.State, plan, use_goal_channel, targets, mark=FOLLOW_MARK):
    """int32 (): moves from the agent to targets' heading taking, at every move, the unvisited
    neighbour the plan marks most strongly (:func:`_follow_candidates`); -1 if that does not
    arrive within 2 (H + W) moves."""
    heading = targets[0]
    h, w = state.seen.shape
    limit = 2 * (h + w)

    def walking(carry):
        _, moves, arrived, stuck = carry
        return ~arrived & ~stuck & (moves < limit)

    def body(carry):
        # Where psi cannot step on (nothing ahead) the walk ends: it would stay put.
        s, moves, _, _ = carry
        cells, _, score, _, ahead = _follow_candidates(s, plan, use_goal_channel, targets,
                                                       mark)
        nxt = jnp.where(ahead, cells[jnp.argmax(score)], s.agent).astype(jnp.int32)
        s = s.replace(agent=nxt, visited=s.visited | env._cell_mask(nxt, w))
        return s, moves + ahead.astype(jnp.int32), jnp.all(nxt == heading), ~ahead

    start = (state, jnp.int32(0), jnp.all(state.agent == heading), jnp.bool_(False))
    _, moves, arrived, _ = jax.lax.while_loop(walking, body, start)
    return jnp.where(arrived, moves, -1).astype(jnp.int32)


def _branch_moves(state: env.State, plan, use_goal_channel, targets, mark=FOLLOW_MARK):
    """(moves int32 (4,), score float32 (4,), cells, legal, heading): for each neighbour N, E,
    S, W that psi_follow may step onto (score finite, :func:`_follow_candidates`), 1 + the
    moves of :func:`_replay_moves` from there: the moves to the heading along that branch of
    the plan's marks; -1 for a branch that does not arrive and for the other neighbours."""
    cells, legal, score, heading, _ = _follow_candidates(state, plan, use_goal_channel, targets,
                                                         mark)
    w = state.seen.shape[1]
    inside = jnp.clip(cells, 0, jnp.array(state.seen.shape) - 1).astype(jnp.int32)

    def from_cell(cell):
        s = state.replace(agent=cell, visited=state.visited | env._cell_mask(cell, w))
        return _replay_moves(s, plan, use_goal_channel, targets, mark)

    moves = jax.vmap(from_cell)(inside)
    ok = jnp.isfinite(score) & (moves >= 0)
    return jnp.where(ok, moves + 1, -1).astype(jnp.int32), score, cells, legal, heading


def follow_moves(state: env.State, plan, use_goal_channel: bool = True,
                 mark: float = FOLLOW_MARK):
    """int32 (): the moves psi_follow would take along this plan (plan float32 (H, W, G)) from
    the agent to the cell the plan heads for (:func:`goal_estimate`), replayed on what the
    agent knows (unseen cells free): its first move onto the branch of the plan's marks that
    arrives soonest (:func:`_branch_moves`), then every move onto the unvisited neighbour
    marked most strongly; -1 if no branch arrives that way within 2 (H + W) moves (psi would
    stop beside unmarked cells, step back onto its track, or walk off along another leg of
    the path). The rule is psi_follow's own, not a search over the map."""
    targets = _follow_targets(state, plan, use_goal_channel)
    moves = _branch_moves(state, plan, use_goal_channel, targets, mark)[0]
    big = jnp.iinfo(jnp.int32).max
    best = jnp.min(jnp.where(moves >= 0, moves, big))
    return jnp.where(best < big, best, -1).astype(jnp.int32)


def psi_follow(state: env.State, plan, use_goal_channel: bool = True,
               mark: float = FOLLOW_MARK):
    """The paper's psi: the move (int32 () in 0..3) onto the legal neighbour the plan marks
    most strongly as path (ties to the lowest move index N, E, S, W), among the marked
    neighbours from which the plan's marks lead on to the cell it heads for
    (:func:`_branch_moves`) if there are any: where the drawn path forks (its leg after the
    reference passing beside the agent), the branch that arrives; where none is marked, the
    legal neighbour nearest (in moves, obstacles ignored) to the cell the plan heads for (move
    0 if no neighbour is legal). See the module docstring."""
    targets = _follow_targets(state, plan, use_goal_channel)
    moves, score, cells, legal, heading = _branch_moves(state, plan, use_goal_channel, targets,
                                                        mark)
    arriving = jnp.where(moves >= 0, score, -jnp.inf)
    follow = jnp.where(jnp.any(moves >= 0), jnp.argmax(arriving), jnp.argmax(score))
    distance = jnp.abs(cells - heading[None, :]).sum(-1)
    greedy = jnp.argmin(jnp.where(legal, distance, jnp.iinfo(jnp.int32).max))
    return jnp.where(jnp.isfinite(score[follow]), follow, greedy).astype(jnp.int32)


def _argmax_cell(values, excluded):
    """int32 (2,): the argmax cell of values float32 (H, W) among cells not excluded."""
    flat = jnp.argmax(jnp.where(excluded, -jnp.inf, values).ravel())
    return jnp.stack([flat // values.shape[1], flat % values.shape[1]]).astype(jnp.int32)


def psi(state: env.State, plan, path_weight: float = 2.0, use_goal_channel: bool = True):
    """The next move (int32 () in 0..3) following the plan; see the module docstring.

    plan: float32 (H, W, G) in [-1, 1] (path, goal estimate[, sub-goal]).
    use_goal_channel=False heads for the far end of the plan's path instead (for models
    trained without goal channels).
    """
    known_obstacle = known_obstacles(state)
    passable = ~known_obstacle
    path01 = (jnp.clip(plan[..., 0], -1.0, 1.0) + 1.0) / 2.0
    enter_cost = 1.0 + path_weight * (1.0 - path01)
    heading = goal_estimate(state, plan, use_goal_channel)
    if use_goal_channel and plan.shape[-1] >= 3:
        goal = goal_cell(plan, known_obstacle)
        avoid = env._cell_mask(goal, plan.shape[1]) & jnp.any(goal != heading)
        enter_cost = enter_cost + AVOID_GOAL_COST * avoid
    field = bfs.cost_to_go(passable, heading, enter_cost)
    return bfs.best_move(field, passable, state.agent, enter_cost)


@dataclasses.dataclass(frozen=True)
class GridTask:
    """diffplan.task.Task for a grid-world setting (hashable; pass as a static argument).

    config: the world's GridConfig. path_weight: psi's preference for the plan's path cells.
    use_goal_channel: False for models trained without goal channels (the ablation "- g").
    num_gen_channels: G of the denoiser that plans it (3, or 2 for models without a sub-goal).
    psi_kind: "search" (:func:`psi`) or "follow" (the paper's psi, :func:`psi_follow`; the
      rollout then plans again where the plan marks no neighbour, ``follows_plan``).
    follow_mark: the path value above which psi_follow reads a cell as marked
      (:data:`FOLLOW_MARK`).
    text: what ``tokens(episode)`` hands the planner: "tokens" (the instruction's token ids)
      or "features" (its pretrained text features, ``Episode.features``, filled on the host by
      ``envs.gridworld.sentences.with_features``: a denoiser with
      ``DenoiserConfig.context_dim`` > 0).
    """

    config: GridConfig
    path_weight: float = 2.0
    use_goal_channel: bool = True

    @property
    def height(self) -> int:
        return self.config.size

    @property
    def width(self) -> int:
        return self.config.size

    num_cond_channels: int = NUM_COND_CHANNELS
    num_gen_channels: int = NUM_GEN_CHANNELS
    psi_kind: str = "search"
    follow_mark: float = FOLLOW_MARK
    text: str = "tokens"

    def __post_init__(self):
        if self.text not in TEXT_INPUTS:
            raise ValueError(f"text must be one of {TEXT_INPUTS}, got {self.text!r}")
        if self.num_cond_channels != NUM_COND_CHANNELS:
            raise ValueError(f"the grid world has {NUM_COND_CHANNELS} condition channels, got "
                             f"num_cond_channels={self.num_cond_channels}")
        if self.num_gen_channels not in (2, 3):
            raise ValueError("num_gen_channels must be 3 (path, goal, sub-goal) or 2 (path, "
                             f"goal: models without a sub-goal), got {self.num_gen_channels}")
        if not self.path_weight >= 0:
            raise ValueError(f"path_weight must be >= 0, got {self.path_weight}")
        if self.psi_kind not in PSI_KINDS:
            raise ValueError(f"psi_kind must be one of {PSI_KINDS}, got {self.psi_kind!r}")
        check_follow_mark(self.follow_mark)

    @property
    def follows_plan(self) -> bool:
        """psi only follows the plan's marks (the rollout plans again where it cannot)."""
        return self.psi_kind == "follow"

    @property
    def max_steps(self) -> int:
        return self.config.max_steps

    def reset(self, episode: Episode) -> env.State:
        return env.reset(episode, self.config)

    def condition(self, state: env.State):
        return condition_from_observation(env.observe(state, self.config))

    def tokens(self, episode: Episode):
        """int32 (L,) token ids, or with text "features" float32 (L, D) features."""
        if self.text == "tokens":
            return episode.tokens
        if episode.features is None:
            raise ValueError("these episodes carry no instruction features: fill them with "
                             "envs.gridworld.sentences.with_features before the rollout")
        return episode.features

    def psi(self, state: env.State, plan):
        if self.follows_plan:
            return psi_follow(state, plan, self.use_goal_channel, self.follow_mark)
        return psi(state, plan, self.path_weight, self.use_goal_channel)

    def unfollowable(self, state: env.State, plan):
        """bool (): psi_follow would fall back on this plan (used when follows_plan)."""
        return unfollowable(state, plan, self.use_goal_channel, self.follow_mark)

    def step(self, state: env.State, action):
        return env.step(state, action, self.config)

    def done(self, state: env.State):
        return env.done(state)

    def position(self, state: env.State):
        return state.agent

    def new_information(self, old_condition, condition):
        """bool (): a cell's token (channel 0) differs: newly seen cells (objects and
        obstacles never move, so nothing else changes what is known of the world)."""
        return jnp.any(old_condition[..., 0] != condition[..., 0])

    def plan_refuted(self, state: env.State, plan):
        """bool (): the plan's guess is disproved by what has been seen (the "on_refuted"
        re-planning trigger; :func:`plan_refuted`); with psi_kind "follow" also where psi,
        replaying the plan's marks, would not arrive where the plan heads
        (:func:`follow_moves` -1: a kept plan would walk the agent back and forth over its own
        track, or off along the path's other leg)."""
        refuted = plan_refuted(state, plan, self.use_goal_channel)
        if self.follows_plan:
            refuted = refuted | (follow_moves(state, plan, self.use_goal_channel,
                                              self.follow_mark) < 0)
        return refuted

    def plan_cost(self, state: env.State, plan):
        """float32 (): how far the plan sends the agent, a refuted plan last (the ranking of
        several drawn plans, ``PlannerConfig.samples``; :func:`plan_cost`); with psi_kind
        "follow" a plan along whose marks psi_follow would not arrive where it heads
        (:func:`follow_moves` -1: a path broken, or one whose later leg draws the agent away
        from its sub-goal) also costs REFUTED_PLAN_COST more."""
        cost = plan_cost(state, plan, self.use_goal_channel)
        if self.follows_plan:
            moves = follow_moves(state, plan, self.use_goal_channel, self.follow_mark)
            cost = cost + REFUTED_PLAN_COST * (moves < 0)
        return cost

    def at_goal_estimate(self, state: env.State, plan):
        """bool (): the agent stands on the cell the plan heads for (with a sub-goal channel:
        its argmax off known obstacles, visited or not, so that arriving there counts)."""
        if self.use_goal_channel and plan.shape[-1] >= 3:
            known_obstacle = known_obstacles(state)
            return jnp.all(state.agent == _argmax_cell(plan[..., 2], known_obstacle))
        return jnp.all(state.agent == goal_estimate(state, plan, self.use_goal_channel))
