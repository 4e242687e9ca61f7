"""The grid world's training data: supervised examples for the in-painting denoiser.

An example is a state the agent can be in (along an expert path, or a few random moves off it)
and the plan from there (the targets of the generated channels, see :func:`training_example`).
:class:`Recipe` is the recipe the shipped denoiser was trained with: one denoiser for the three
settings, trained on a fixed mixture of them per batch (TRAINING_MIXTURE), half of the examples
with detours, the goal channels weighted 3x in the loss.

Training episodes come from ``fold_in(step key, TRAIN_STREAM)`` (:func:`training_episode_keys`),
never of the form ``fold_in(PRNGKey(seed), i)`` that evaluation episodes use.
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from diffplan.language import (check_dropout_rate, check_training_language, drop_words,
                               slot_roles)
from envs.gridworld import bfs, env, grammar
from envs.gridworld.config import GridConfig, make_config
from envs.gridworld.episode import Episode, expert_path_positions, generate, OBSTACLE_CELL
from envs.gridworld.task import AGENT_CHANNEL, NUM_GEN_CHANNELS, condition_from_observation

TRAIN_STREAM = 0x7EA1
TRAINING_MIXTURE = (("p_mo2g", 36), ("mo1g", 18), ("1o1g", 10))
"""Examples of each setting per batch of 64 (one denoiser serves the three settings)."""
EXAMPLE_KEYS = 5
"""An example's key splits into this many; the first generates its episode."""
SEARCH_STREAM = 0x5EA
"""The searcher-route draws of an example (:func:`training_example`, ``search_prob``) use
``fold_in(example key, SEARCH_STREAM)``, so the other draws stay those of a recipe without."""
MAX_SEARCH_MOVES = 16
"""A searcher-route example stops after 0..MAX_SEARCH_MOVES of the searcher's moves past the
reference (fewer if it reached the target)."""
STRAY_STREAM = 0x57A
"""The stray-walk draws of an example (:func:`training_example`, ``stray_prob``) use
``fold_in(example key, STRAY_STREAM)``, so the other draws stay those of a recipe without."""
MAX_STRAY_MOVES = 12
"""A stray example's agent takes 1..MAX_STRAY_MOVES moves toward the target (fewer where it
stands beside it)."""


def state_along_expert(episode: Episode, config: GridConfig, index):
    """The state after following the expert path for ``index`` moves (int32 ())."""
    positions = episode.expert_positions  # (P, 2)
    steps = jnp.arange(positions.shape[0])
    taken = steps <= index
    size = config.size
    fovs = jax.vmap(lambda p: env.field_of_view(p, size, config.view_radius))(positions)
    seen = jnp.any(fovs & taken[:, None, None], axis=0)
    visited = bfs.positions_to_mask(positions, size, taken)
    agent = positions[index]
    if config.has_reference:
        on_ref = jnp.all(positions == episode.reference, axis=-1)
        reached_reference = jnp.any(on_ref & taken)
    else:
        reached_reference = jnp.array(False)
    on_target = jnp.all(agent == episode.target)
    return env.State(
        grid=episode.grid, agent=agent, target=episode.target, reference=episode.reference,
        seen=seen, visited=visited, t=index.astype(jnp.int32), collisions=jnp.int32(0),
        reached_reference=reached_reference, done=on_target, success=on_target,
    )


def _random_detour(key, state: env.State, config: GridConfig, num_moves, max_moves: int):
    """The state after ``num_moves`` (int32 () <= max_moves, static) uniformly random moves
    from ``state`` (moves into obstacles or off the grid stay in place, as in the world)."""
    actions = jax.random.randint(key, (max_moves,), 0, 4)
    return _walk(state, config, num_moves, max_moves, lambda s, i: actions[i])


def _walk(state: env.State, config: GridConfig, num_moves, max_moves: int, action_of,
          keep_going=None):
    """The state after ``num_moves`` (int32 () <= max_moves, static) moves, move i being
    ``action_of(state, i)`` (a done state stays as it is: env.step); with ``keep_going(state,
    i)`` (bool ()), the walk also stops at the first state where it is False."""

    def move(s, i):
        moved = env.step(s, action_of(s, i), config)
        go = i < num_moves
        if keep_going is not None:
            go = go & keep_going(s, i)
        return jax.tree.map(lambda new, old: jnp.where(go, new, old), moved, s), None

    state, _ = jax.lax.scan(move, state, jnp.arange(max_moves))
    return state


def _stray_walk(state: env.State, config: GridConfig, num_moves, max_moves: int):
    """The state after ``num_moves`` (int32 () <= max_moves, static) moves along a shortest
    path (whole map known) toward the target from ``state``, stopping beside the target (it
    is never entered): where an agent that took the route's later leg too early stands, the
    reference not yet stood on."""
    passable = state.grid != OBSTACLE_CELL
    field = bfs.cost_to_go(passable, state.target)

    def action_of(s, i):
        return bfs.best_move(field, passable, s.agent)

    def keep_going(s, i):
        return field[s.agent[0], s.agent[1]] > 1

    return _walk(state, config, num_moves, max_moves, action_of, keep_going)


def _searcher_walk(state: env.State, tokens, config: GridConfig, num_moves,
                   max_moves: int):
    """The state after ``num_moves`` (int32 () <= max_moves, static) moves of the searcher
    (``envs.gridworld.agents.searcher_move``: nothing learned, it sees what the agent sees) from
    ``state`` (a done state stays as it is)."""
    from envs.gridworld.agents import searcher_move

    def action_of(s, i):
        return searcher_move(condition_from_observation(env.observe(s, config)), tokens)

    return _walk(state, config, num_moves, max_moves, action_of)


def _route_cells(positions, valid, reference, pending, size: int, later_leg_value: float):
    """float32 (H, W): the path channel's target of a route (positions int32 (P, 2), valid bool
    (P,) its entries): ``1`` on the cells up to its first visit of the reference (the whole
    route when ``pending`` (bool ()) is False: no reference left to reach), ``later_leg_value``
    on the cells only the rest of the route passes, ``-1`` off the route."""
    at_reference = jnp.all(positions == reference, axis=-1) & valid & pending
    first = jnp.where(at_reference.any(), jnp.argmax(at_reference), positions.shape[0])
    current = bfs.positions_to_mask(positions, size, valid & (jnp.arange(positions.shape[0])
                                                              <= first))
    route = bfs.positions_to_mask(positions, size, valid)
    return jnp.where(current, 1.0, jnp.where(route, later_leg_value, -1.0)).astype(jnp.float32)


def _expert_from(state: env.State, episode: Episode, config: GridConfig,
                 later_leg_value: float = 1.0):
    """float32 (H, W): the path channel's target (:func:`_route_cells`) of a shortest path from
    the agent's cell through the reference (unless already reached) to the target, ends
    included."""
    passable = episode.grid != OBSTACLE_CELL
    pending = jnp.asarray(config.has_reference) & ~state.reached_reference
    reference = (jnp.where(state.reached_reference, state.agent, episode.reference)
                 if config.has_reference else episode.reference)
    positions, length, _ = expert_path_positions(config, passable, state.agent, episode.target,
                                                 reference)
    valid = jnp.arange(positions.shape[0]) <= length
    return _route_cells(positions, valid, episode.reference, pending, config.size,
                        later_leg_value)


def training_example(key, config: GridConfig, detour_prob: float = 0.0, max_detour: int = 8,
                     later_leg_value: float = 1.0, search_prob: float = 0.0,
                     stray_prob: float = 0.0, instruction=None):
    """One supervised example: a state along an expert path and the plan from there.

    The agent is placed after a uniformly drawn number of expert moves (0..expert_length - 1)
    with the field of view accumulated along the way. With probability ``detour_prob`` it then
    takes 1..max_detour uniformly random moves (so the model also sees the states an imperfect
    on-the-fly agent reaches). With probability ``search_prob`` (settings whose target lies
    beyond the reference's view only: P-MO2G-far) the agent instead walks the expert path to
    the reference, then 0..MAX_SEARCH_MOVES moves of the searcher's exploration of the
    instructed sector (``envs.gridworld.agents``): states an agent that searches reaches, with
    parts of the sector seen and empty, which the expert's walk straight to the target never
    shows. With probability ``stray_prob`` (settings with a reference), an agent that has not
    yet stood on the reference then takes 1..MAX_STRAY_MOVES moves along a shortest path
    toward the target, stopping beside it: the states of an agent that took the route's later
    leg too early (at a fork where the plan marks both legs), whose plan must still name the
    reference. Targets of the generated channels (envs.gridworld.task):
      path      a shortest path from there (through the reference unless it was reached) to
                the target, ends included (without a detour: the rest of the expert path):
                +1 on its cells up to the reference (all of them once the reference was
                reached, and in the settings without one), ``later_leg_value`` on the cells
                only its leg from the reference to the target passes, -1 elsewhere (below 1 the
                plan tells the leg the agent is on from the next one, which psi_follow needs
                where the two legs run side by side or overlap);
      goal      the target cell, whether or not it has been seen (the model must infer it from
                the instruction and the reference);
      sub-goal  the reference while the agent has not stood on it (P-MO2G), else the target.

    instruction: what the example carries of its episode's instruction, ``instruction(episode)``
    (default the token ids, ``episode.tokens``; a features recipe: its sentence ids,
    :func:`instruction_sentence_ids`).

    Returns (x0 float32 (H, W, C + 3), tokens int32 (L,) (or what ``instruction`` gives),
    seen bool (H, W)).
    """
    k_episode, k_index, k_detour, k_moves, k_walk = jax.random.split(key, EXAMPLE_KEYS)
    episode = generate(k_episode, config)
    length = jnp.maximum(episode.expert_length, 1)
    index = jax.random.randint(k_index, (), 0, length)
    search = search_prob > 0 and config.target_beyond_reference_view
    if search:
        k_search, k_search_moves = jax.random.split(jax.random.fold_in(key, SEARCH_STREAM))
        searching = jax.random.bernoulli(k_search, search_prob)
        at_reference = jnp.all(episode.expert_positions == episode.reference, axis=-1)
        index = jnp.where(searching, jnp.argmax(at_reference), index)
    state = state_along_expert(episode, config, index)
    walked = jnp.bool_(False)  # a searcher or stray walk placed the agent (no detour then)
    if search:
        num_search = jax.random.randint(k_search_moves, (), 0, MAX_SEARCH_MOVES + 1)
        state = _searcher_walk(state, episode.tokens, config,
                               jnp.where(searching, num_search, 0), MAX_SEARCH_MOVES)
        walked = searching
    stray = stray_prob > 0 and config.has_reference
    if stray:
        k_stray, k_stray_moves = jax.random.split(jax.random.fold_in(key, STRAY_STREAM))
        straying = (jax.random.bernoulli(k_stray, stray_prob) & ~state.reached_reference
                    & ~state.done & ~walked)
        num_stray = jax.random.randint(k_stray_moves, (), 1, MAX_STRAY_MOVES + 1)
        state = _stray_walk(state, config, jnp.where(straying, num_stray, 0), MAX_STRAY_MOVES)
        walked = walked | straying
    if detour_prob > 0 or search or stray:
        detour = jax.random.bernoulli(k_detour, detour_prob) & ~state.done & ~walked
        num_moves = jnp.where(detour, jax.random.randint(k_moves, (), 1, max_detour + 1), 0)
        state = _random_detour(k_walk, state, config, num_moves, max_detour)
        path = _expert_from(state, episode, config, later_leg_value)
    else:
        steps = jnp.arange(episode.expert_positions.shape[0])
        remaining = (steps >= index) & (steps <= episode.expert_length)
        pending = jnp.asarray(config.has_reference) & ~state.reached_reference
        path = _route_cells(episode.expert_positions, remaining, episode.reference, pending,
                            config.size, later_leg_value)
    obs = env.observe(state, config)
    goal = env._cell_mask(episode.target, config.size)
    if config.has_reference:
        next_cell = jnp.where(state.reached_reference, episode.target, episode.reference)
    else:
        next_cell = episode.target
    subgoal = env._cell_mask(next_cell, config.size)
    signed = lambda mask: (mask.astype(jnp.float32) * 2 - 1)[..., None]  # noqa: E731
    x0 = jnp.concatenate([condition_from_observation(obs), path[..., None], signed(goal),
                          signed(subgoal)], axis=-1)
    return x0, episode.tokens if instruction is None else instruction(episode), state.seen


def instruction_sentence_ids(episode: Episode, config: GridConfig):
    """int32 (S,) the rows of the episode's instruction's sentences in the training sentence
    table (``envs.gridworld.sentences.training_index``; -1 = absent)."""
    from envs.gridworld.sentences import training_index

    return training_index().ids(config.has_reference, episode.template,
                                episode.reference_class, episode.target_class,
                                episode.direction)


# ------------------------------------------------------------------------------ batches

def training_episode_keys(key, batch_size: int):
    """The episode keys of one training batch: (batch_size,) keys from the TRAIN_STREAM fold
    of the step's key (never of the form fold_in(PRNGKey(seed), i) used for evaluation)."""
    return jax.random.split(jax.random.fold_in(key, TRAIN_STREAM), batch_size)


def near_agent(agent):
    """bool (H, H): the agent's cell and its 4 neighbours (``bfs.neighbours``, those on the
    grid), from the agent mask (H, H) (the condition's agent channel); the cells psi_follow
    chooses the next move among."""
    size = agent.shape[0]
    flat = jnp.argmax(agent.ravel() > 0)
    cell = jnp.stack([flat // size, flat % size])
    cells, inside = bfs.neighbours(cell, agent.shape)
    return bfs.positions_to_mask(jnp.concatenate([cell[None], cells]), size,
                                 jnp.concatenate([jnp.array([True]), inside]))


def make_batch_fn(config: GridConfig, goal_channel: bool = True,
                  goal_loss_seen_only: bool = False, detour_prob: float = 0.0,
                  goal_loss_weight: float = 1.0, path_near_agent_weight: float = 0.0,
                  later_leg_value: float = 1.0, role_loss_weight: float = 0.0,
                  search_prob: float = 0.0, stray_prob: float = 0.0, text: str = "tokens"):
    """batch_fn(key, batch_size) -> diffplan.train.Batch of examples of one setting.

    goal_channel=False trains without goal information (the paper's "- g" ablation: the goal
    and sub-goal channels are dropped from the loss). goal_loss_seen_only masks the goal loss
    to seen cells. detour_prob: the share of examples whose agent left the expert path by a
    few random moves (:func:`training_example`). goal_loss_weight: the weight of the goal and
    sub-goal channels in the loss relative to the path channel's (each is one cell of H x W).
    path_near_agent_weight: extra weight of the path channel on the agent's cell and its 4
    neighbours (:func:`near_agent`; 0: every cell weighs 1), where the plan's path decides the
    next move of the paper's psi (``GridTask(psi_kind="follow")``). later_leg_value: the path
    target on the route's leg after the reference (:func:`training_example`; 1: one value
    for the whole route). role_loss_weight: 0, or the weight of an auxiliary loss
    (``diffplan.losses.token_loss``) asking the denoiser's token head which slot each slot word
    fills (:data:`ROLES`, ``diffplan.language.slot_roles``); it needs ``token_classes=3``.
    search_prob: the share of examples placed along the searcher's exploration past the
    reference (:func:`training_example`; used only where the target is hidden from the
    reference, P-MO2G-far). stray_prob: the share of examples whose agent walked toward the
    target before standing on the reference (:func:`training_example`; settings with a
    reference). text: "tokens" (the batch's tokens are token ids) or "pretrained" (the rows
    of the instruction's sentences in the training sentence table, int32 (B, S), which
    ``diffplan.train.train(..., sentences=table)`` assembles into features).
    """
    if not role_loss_weight >= 0:
        raise ValueError(f"role_loss_weight must be >= 0, got {role_loss_weight}")
    if not 0 < later_leg_value <= 1:
        raise ValueError(f"later_leg_value must be in (0, 1], got {later_leg_value}")
    if not path_near_agent_weight >= 0:
        raise ValueError(f"path_near_agent_weight must be >= 0, got {path_near_agent_weight}")
    if not goal_loss_weight > 0:
        raise ValueError(f"goal_loss_weight must be > 0, got {goal_loss_weight}")
    if not 0 <= detour_prob <= 1:
        raise ValueError(f"detour_prob must be in [0, 1], got {detour_prob}")
    if not 0 <= search_prob <= 1:
        raise ValueError(f"search_prob must be in [0, 1], got {search_prob}")
    if not 0 <= stray_prob <= 1:
        raise ValueError(f"stray_prob must be in [0, 1], got {stray_prob}")
    from diffplan.losses import with_token_labels
    from diffplan.train import Batch

    check_text(text, role_loss_weight=role_loss_weight)
    templates = grammar.compile_templates(config.setting)
    instruction = (functools.partial(instruction_sentence_ids, config=config)
                   if text == "pretrained" else None)

    def batch_fn(key, batch_size):
        keys = training_episode_keys(key, batch_size)
        example = functools.partial(training_example, config=config, detour_prob=detour_prob,
                                    later_leg_value=later_leg_value, search_prob=search_prob,
                                    stray_prob=stray_prob, instruction=instruction)
        x0, tokens, seen = jax.vmap(example)(keys)
        ones = jnp.ones(x0.shape[:-1], jnp.float32)
        path = ones + path_near_agent_weight * jax.vmap(near_agent)(x0[..., AGENT_CHANNEL])
        goal = goal_loss_weight * (seen.astype(jnp.float32) if goal_loss_seen_only else ones)
        subgoal = goal_loss_weight * ones
        if not goal_channel:
            goal, subgoal = jnp.zeros_like(goal), jnp.zeros_like(subgoal)
        mask = jnp.stack([path, goal, subgoal], axis=-1)
        if text == "pretrained":
            return Batch(x0=x0, tokens=tokens, loss_mask=mask)
        roles, named = jax.vmap(lambda t: slot_roles(t, templates))(tokens)
        return with_token_labels(Batch(x0=x0, tokens=tokens, loss_mask=mask), roles, named,
                                 role_loss_weight)

    return batch_fn


TEXTS = ("tokens", "pretrained")
"""How a recipe gives the denoiser its instructions (``Recipe.text``): token ids of the
grammar's vocabulary, or the frozen pretrained text encoder's features of each sentence
(``diffplan.instruction``; the batches carry sentence ids, assembled inside the step)."""


def check_text(text: str, word_dropout: float = 0.0, role_loss_weight: float = 0.0) -> None:
    """ValueError (one line) for an unknown text input, or for what needs word tokens with
    pretrained features (word dropout, token labels)."""
    if text not in TEXTS:
        raise ValueError(f"text must be one of {TEXTS}, got {text!r}")
    if text == "pretrained" and word_dropout:
        raise ValueError("word dropout drops word tokens: the pretrained text features have "
                         "none (use word_dropout=0 with text='pretrained')")
    if text == "pretrained" and role_loss_weight:
        raise ValueError("the role loss labels word tokens: the pretrained text features have "
                         "none (use role_loss_weight=0 with text='pretrained')")


ROLES = ("reference", "target", "direction")
"""The classes of the grid world's token roles: the slot a word fills (grammar slot k is
role k), whatever the phrasing's word order."""


SLOT_WORD_IDS = np.concatenate([
    grammar.class_to_token(np.arange(1, len(grammar.OBJECT_NAMES) + 1)),
    grammar.DIRECTION_TOKEN_IDS]).astype(np.int32)
"""Token ids of the words that fill an instruction's slots (object names, compass directions):
what word dropout never drops."""


def make_mixture_batch_fn(mixture=TRAINING_MIXTURE, goal_channel: bool = True,
                          language: str = "canonical", word_dropout: float = 0.0,
                          text: str = "tokens", **example_kwargs):
    """batch_fn(key, batch_size) -> Batch with the settings' examples in fixed proportions:
    mixture ((setting, count), ...) gives count examples of each setting per sum(counts) (the
    batch size must be a multiple of sum(counts)); example j of setting s comes from
    training_episode_keys(fold_in(key, index of s), ...). language: the phrasing of the
    instructions (GridConfig.language; never "unseen"). word_dropout: the probability that a
    word other than a slot filler (:data:`SLOT_WORD_IDS`) becomes padding
    (diffplan.language.drop_words, with a key of its own, so the episodes do not change).
    text: "tokens" or "pretrained" (:func:`make_batch_fn`). example_kwargs go to
    :func:`make_batch_fn`."""
    check_training_language(language)
    check_dropout_rate(word_dropout, "word_dropout")
    check_text(text, word_dropout)
    total = sum(count for _, count in mixture)
    fns = [(make_batch_fn(make_config(setting, language=language), goal_channel, text=text,
                          **example_kwargs), count)
           for setting, count in mixture]

    def batch_fn(key, batch_size):
        if batch_size % total:
            raise ValueError(f"batch size {batch_size} is not a multiple of the mixture's "
                             f"{total} examples {mixture}")
        scale = batch_size // total
        parts = [fn(jax.random.fold_in(key, i), count * scale)
                 for i, (fn, count) in enumerate(fns)]
        batch = jax.tree.map(lambda *xs: jnp.concatenate(xs), *parts)
        if text == "pretrained":
            return batch
        return batch._replace(tokens=drop_words(jax.random.fold_in(key, len(fns)),
                                                batch.tokens, word_dropout, SLOT_WORD_IDS))

    return batch_fn


@dataclasses.dataclass(frozen=True)
class Recipe:
    """The grid world's training-data recipe (what ``experiments.compile_*`` --train uses).

    mixture: (setting, examples per batch of sum(counts)). detour_prob / goal_loss_weight: see
    :func:`make_batch_fn`, and so are path_near_agent_weight and later_leg_value (the path
    target on the route's leg after the reference). goal_channel: False for the "- g"
    ablation. language: the phrasing of the examples' instructions ("mixed": canonical half of
    the time, else one of the training paraphrases; the held-out phrasings never).
    word_dropout: the probability that a training instruction's word other than an object name
    or direction is dropped (0: none; see :func:`make_mixture_batch_fn`). role_loss_weight: 0,
    or the weight of the auxiliary slot-role loss (:func:`make_batch_fn`; the denoiser needs
    ``token_classes=3``). search_prob: the share of P-MO2G-far examples placed along the
    searcher's exploration of the instructed sector (:func:`training_example`). stray_prob: the
    share of examples of the settings with a reference whose agent walked toward the target
    before standing on the reference (:func:`training_example`). text: "tokens" (the grammar's
    token ids) or "pretrained" (the frozen pretrained text encoder's features of each
    sentence, ``diffplan.instruction``: the batches carry sentence ids into
    :meth:`sentences`, the training sentence table; no word dropout, no role loss).
    """

    mixture: tuple = TRAINING_MIXTURE
    detour_prob: float = 0.5
    goal_loss_weight: float = 3.0
    goal_channel: bool = True
    language: str = "mixed"
    path_near_agent_weight: float = 0.0
    later_leg_value: float = 1.0
    word_dropout: float = 0.0
    role_loss_weight: float = 0.0
    search_prob: float = 0.0
    stray_prob: float = 0.0
    text: str = "tokens"

    def __post_init__(self):
        check_text(self.text, self.word_dropout, self.role_loss_weight)
        check_training_language(self.language)

    def batch_fn(self):
        return make_mixture_batch_fn(self.mixture, self.goal_channel, self.language,
                                     word_dropout=self.word_dropout, text=self.text,
                                     detour_prob=self.detour_prob,
                                     goal_loss_weight=self.goal_loss_weight,
                                     path_near_agent_weight=self.path_near_agent_weight,
                                     later_leg_value=self.later_leg_value,
                                     role_loss_weight=self.role_loss_weight,
                                     search_prob=self.search_prob,
                                     stray_prob=self.stray_prob)

    @property
    def batch_multiple(self) -> int:
        """A batch size must be a multiple of this: the mixture's examples per batch."""
        return sum(count for _, count in self.mixture)

    def init_batch(self):
        """Shapes of one example (every setting's examples have the same shapes; with text
        "pretrained" its tokens are sentence ids)."""
        fn = make_batch_fn(make_config(self.mixture[0][0]),
                           role_loss_weight=self.role_loss_weight, text=self.text)
        return jax.eval_shape(lambda k: fn(k, 1), jax.random.PRNGKey(0))

    def sentences(self):
        """The training sentence table the batches' sentence ids index
        (``envs.gridworld.sentences.training_table``; computed once, then read from the disk
        cache), or None with text "tokens"."""
        if self.text == "tokens":
            return None
        from envs.gridworld.sentences import training_table

        return training_table()

    def fixed_params(self, model_config) -> dict | None:
        """The model's constants written before training: for a denoiser that embeds cells by
        their names (``DenoiserConfig.cell_context``), the encoder's features of the cell
        tokens' names, and with ``standardize`` the training sentences' feature statistics
        (``diffplan.instruction.fixed_text_params``); else None."""
        from diffplan.instruction import fixed_text_params
        from envs.gridworld.sentences import instruction_encoder

        return fixed_text_params(model_config, grammar.CELL_TOKENS, instruction_encoder,
                                 self.sentences)

    def text_metadata(self) -> dict:
        """What a checkpoint records of its instruction input: the vocabulary its token ids
        index, or (text "pretrained") the text encoder (files' sha256, L) and the cell tokens
        its grid embedding indexes."""
        if self.text == "tokens":
            return {"vocabulary": list(grammar.VOCAB)}
        from diffplan.instruction import encoder_record
        from envs.gridworld.sentences import instruction_encoder

        encoder = instruction_encoder()
        return {"text": self.text, "cell_tokens": list(grammar.CELL_TOKENS),
                "text_encoder": encoder_record(encoder.encoder, encoder.max_tokens)}

    def metadata(self) -> dict:
        """What a checkpoint records of the recipe (compared when resuming)."""
        return {"mixture": [list(m) for m in self.mixture], "goal_channel": self.goal_channel,
                "detour_prob": self.detour_prob, "goal_loss_weight": self.goal_loss_weight,
                "language": self.language, "num_gen_channels": NUM_GEN_CHANNELS,
                **self.text_metadata(),
                # Recorded only when used, so that checkpoints from before it existed match.
                **({"path_near_agent_weight": self.path_near_agent_weight}
                   if self.path_near_agent_weight else {}),
                **({"later_leg_value": self.later_leg_value}
                   if self.later_leg_value != 1.0 else {}),
                **({"word_dropout": self.word_dropout} if self.word_dropout else {}),
                **({"role_loss_weight": self.role_loss_weight}
                   if self.role_loss_weight else {}),
                **({"search_prob": self.search_prob} if self.search_prob else {}),
                **({"stray_prob": self.stray_prob} if self.stray_prob else {})}


# ------------------------------------------------------------------ the episodes of a run

@functools.partial(jax.jit, static_argnums=(2, 3, 4))
def _episodes_of_steps(step_ids, seed, config: GridConfig, index: int, count: int) -> Episode:
    """The episodes of one setting (mixture position ``index``, ``count`` per batch) in the
    batches of training steps ``step_ids`` (S,) of a run of ``seed``: (S * count,) episodes."""
    from diffplan.train_state import step_key

    def one(step):
        batch_key = jax.random.split(step_key(seed, step))[0]
        keys = training_episode_keys(jax.random.fold_in(batch_key, index), count)
        episode_keys = jax.vmap(lambda k: jax.random.split(k, EXAMPLE_KEYS)[0])(keys)
        return jax.vmap(lambda k: generate(k, config))(episode_keys)

    return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), jax.vmap(one)(step_ids))


def training_episodes(setting: str, *, seed: int, steps: int, batch_size: int,
                      mixture=TRAINING_MIXTURE, language: str = Recipe.language,
                      chunk: int = 500) -> Episode:
    """Every episode of ``setting`` that a training run with this mixture saw (as numpy, a
    leading axis of steps x examples per batch), recomputed from the keys the training loop
    gives its steps (``diffplan.train_state.step_key``; the denoiser's step splits it into
    (batch key, loss key), ``make_mixture_batch_fn`` folds the setting's index into the batch
    key, and each example generates its episode from the first of its keys).
    tests/test_training_disjoint.py checks this against the episodes that ``diffplan.train``
    really generates. language: the recipe's (Recipe.language)."""
    import numpy as np

    names = [name for name, _ in mixture]
    if setting not in names:
        raise ValueError(f"{setting!r} is not in the training mixture {mixture}")
    index = names.index(setting)
    total = sum(count for _, count in mixture)
    if batch_size % total:
        raise ValueError(f"batch size {batch_size} is not a multiple of the mixture's {total}")
    count = dict(mixture)[setting] * (batch_size // total)
    config = make_config(setting, language=language)

    parts = []
    for lo in range(0, steps, chunk):
        ids = np.arange(lo, lo + chunk)  # fixed size: one compilation; the tail is dropped
        parts.append(jax.device_get(_episodes_of_steps(ids, seed, config, index, count)))
    episodes = jax.tree.map(lambda *xs: np.concatenate(xs), *parts)
    return jax.tree.map(lambda x: x[:steps * count], episodes)

