"""The Kuka world's training data: supervised examples for the in-painting denoiser.

An example is a state the arm can be in between two placements and the expert's next
pick-and-place from there, drawn as the generated channels of the planning tensor
(:mod:`envs.kuka.task`): the carry path, the support's visible top (goal estimate) and the moved
block's visible top (pick). States are cheap: ``expert.planned_poses`` builds the first k
relations exactly, without physics; with probability ``Recipe.perturb_prob`` the blocks that
were moved are then shifted and turned a little (more than the primitive's measured placement
error, <= 3.4 mm and 0.004 rad over 24 expert placements under physics), so that re-plans see
the small offsets physics produces and the cells they shift on the grid.

The expert's build order (:func:`planner_goal`) is made a function of the instruction: the
instructed relations in instruction order, except that a relation whose bottom block is another
relation's top waits for it; single-constraint stacking builds the instructed pair first and
then stacks the two other blocks on it in colour order (red, green, blue, yellow). The
scripted expert of the CLIs (``--policy expert``) draws the free part of a single-constraint
tower at random (``Episode.goal``); a denoiser trained on a random order would have to guess it.

Training episodes come from ``fold_in(step key, TRAIN_STREAM)`` keys, never of the form
``fold_in(PRNGKey(seed), i)`` that evaluation episodes use.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffplan.instruction import check_text, text_metadata
from diffplan.language import check_training_language
from envs.kuka import expert, grammar, grid, scene
from envs.kuka.config import COLUMNS, TaskSpec
from envs.kuka.episode import Episode, generate
from envs.kuka.sentences import instruction_encoder, training_index, training_table
from envs.kuka.task import NUM_GEN_CHANNELS, condition_from_view

TRAIN_STREAM = 0x6B4B
SPECS = tuple(dataclasses.replace(spec, language=language)
              for language in ("canonical", "paraphrased") for spec in COLUMNS.values())
"""The four Table 2 columns, canonical and paraphrased instructions (Table 5), one share each:
the mixture the Kuka baselines are trained on."""
_SHARES = {"canonical": {("stacking", False): 2, ("rearrangement", False): 1,
                         ("stacking", True): 1, ("rearrangement", True): 1},
           "paraphrased": {("stacking", False): 2, ("rearrangement", False): 1,
                           ("stacking", True): 3, ("rearrangement", True): 5}}
DENOISER_SPECS = tuple(spec for spec in SPECS for _ in range(
    _SHARES[spec.language][spec.kind, spec.multi]))
"""The task specs the shipped denoiser is trained on (``Recipe``'s default): the same eight, in
16 shares of a batch: canonical single-constraint stacking 2, the other canonical columns 1;
paraphrased stacking 2 single / 3 multi, rearrangement 1 single / 5 multi. Chosen on the
validation seed (docs/benchmarks.md): with 10 training timesteps drawn towards the noisy end
(``timestep_power`` 3) and 4600 steps of 32, it reads 100.0 strict SR in every canonical
column and 99.2 on paraphrased multi-constraint rearrangement, where the even mixture read
81.2 after 5600 steps."""
PERTURB_XY = 0.006
"""Standard deviation (m) of the shift of moved blocks in perturbed examples (clipped at 2.5x)."""
PERTURB_YAW = 0.02
"""Standard deviation (rad) of their turn about z (clipped at 2.5x)."""


def single_tower(episode: Episode):
    """bool (): a single-constraint stacking episode, whose instruction opens with the tower
    sentence (``episode.generate``) and whose other two blocks the expert stacks in colour
    order (:func:`planner_goal`)."""
    return episode.tower & ((episode.constraints[:, 0] >= 0).sum() == 1)


def planner_goal(episode: Episode):
    """int32 (3, 2) the relations the training expert builds, in build order (rows of -1
    padding last); see the module docstring."""
    constraints = episode.constraints
    valid = constraints[:, 0] >= 0
    n = constraints.shape[0]
    # Relation i waits for relation j when i's bottom is j's top: depth = relations under it.
    under = (constraints[:, None, 1] == constraints[None, :, 0]) & valid[:, None] & valid[None]
    depth = jnp.zeros(n, jnp.int32)
    for _ in range(n):
        depth = jnp.max(jnp.where(under, depth[None, :] + 1, 0), axis=1)
    order = jnp.argsort(jnp.where(valid, depth * n + jnp.arange(n), n * n + jnp.arange(n)))
    built = constraints[order]
    # Single-constraint tower: the other two blocks on top of the instructed pair, in colour order.
    top, bottom = constraints[0]
    blocks = jnp.arange(scene.NUM_BLOCKS)
    rest = jnp.sort(jnp.where((blocks == top) | (blocks == bottom), scene.NUM_BLOCKS, blocks))
    tower = jnp.stack([constraints[0], jnp.stack([rest[0], top]), jnp.stack([rest[1], rest[0]])])
    return jnp.where(single_tower(episode), tower, built).astype(jnp.int32)


def _yaw_quat(yaw):
    return jnp.stack([jnp.cos(yaw / 2), jnp.zeros_like(yaw), jnp.zeros_like(yaw),
                      jnp.sin(yaw / 2)], axis=-1)


def plan_example(pos, quat, episode: Episode):
    """The planning tensor float32 (24, 24, C + G) of block poses (pos float (4, 3), quat
    (4, 4); nothing held): the view's condition channels, then the expert's next pick-and-place
    (``expert.decide`` with :func:`planner_goal`) as signed maps (+1 / -1): path, goal estimate
    (the support's visible top), pick (the moved block's visible top)."""
    held = jnp.zeros(scene.NUM_BLOCKS, bool)
    step = expert.decide(pos, held, episode.replace(goal=planner_goal(episode)))
    top, height = grid.top_down_view(pos, quat, held)
    maps = jnp.stack([step.path, top == step.support, top == step.block], axis=-1)
    return jnp.concatenate([condition_from_view(top, height),
                            maps.astype(jnp.float32) * 2 - 1], axis=-1)


def training_state(key, spec: TaskSpec, perturb_prob: float):
    """(pos float32 (4, 3), quat float32 (4, 4), episode): a state of a fresh episode of a task
    spec between two placements: the first k relations of :func:`planner_goal` built (k uniform
    among those still to do), blocks moved so far perturbed with probability ``perturb_prob``.
    The episode's goal is the :func:`planner_goal` the state was built by."""
    k_episode, k_built, k_perturb, k_xy, k_yaw = jax.random.split(key, 5)
    episode = generate(k_episode, spec)
    goal = planner_goal(episode)
    count = (goal[:, 0] >= 0).sum()
    built = jax.random.randint(k_built, (), 0, count)
    pos = expert.planned_poses(episode.replace(goal=goal), built)
    moved = jnp.any((jnp.arange(goal.shape[0]) < built)[:, None]
                    & (goal[:, :1] == jnp.arange(scene.NUM_BLOCKS)[None]), axis=0)
    moved = moved & jax.random.bernoulli(k_perturb, perturb_prob)
    shift = PERTURB_XY * jnp.clip(jax.random.normal(k_xy, (scene.NUM_BLOCKS, 2)), -2.5, 2.5)
    yaw = PERTURB_YAW * jnp.clip(jax.random.normal(k_yaw, (scene.NUM_BLOCKS,)), -2.5, 2.5)
    pos = pos.at[:, :2].add(jnp.where(moved[:, None], shift, 0.0))
    quat = _yaw_quat(jnp.where(moved, yaw, 0.0))
    return pos, quat, episode.replace(goal=goal)


def training_example(key, spec: TaskSpec, perturb_prob: float):
    """One example of a task spec: (x0 float32 (24, 24, C + G), tokens int32 (L,), roles int32
    (L,), named bool (L,)): the planning tensor (:func:`plan_example`) of a
    :func:`training_state`, its instruction, and which block each named block token is
    (``grammar.token_roles``)."""
    pos, quat, episode = training_state(key, spec, perturb_prob)
    roles, named = grammar.token_roles(episode.tokens, episode.constraints,
                                       single_tower(episode))
    return plan_example(pos, quat, episode), episode.tokens, roles, named


def instruction_sentence_ids(episode: Episode):
    """int32 (S,) the rows of the episode's instruction's sentences in the training sentence
    table (``envs.kuka.sentences.training_index``; -1 = absent)."""
    return training_index().ids(episode.phrasing, episode.constraints, single_tower(episode))


def sentence_example(key, spec: TaskSpec, perturb_prob: float):
    """One example of a task spec for a denoiser on pretrained text features: (x0 float32
    (24, 24, C + G), sentence ids int32 (S,)): the planning tensor of a :func:`training_state`
    (as :func:`training_example`) and the training-table rows of its instruction's sentences
    (:func:`instruction_sentence_ids`), which ``diffplan.train.train(..., sentences=table)``
    assembles into features inside the step."""
    pos, quat, episode = training_state(key, spec, perturb_prob)
    return plan_example(pos, quat, episode), instruction_sentence_ids(episode)


# ------------------------------------------------------------------------------ batches

def training_episode_keys(key, batch_size: int):
    """The example keys of one training batch: (batch_size,) keys from the TRAIN_STREAM fold
    of the step's key (never of the form fold_in(PRNGKey(seed), i) of evaluation episodes)."""
    return jax.random.split(jax.random.fold_in(key, TRAIN_STREAM), batch_size)


def spec_examples(example_fn, key, batch_size: int, specs, perturb_prob: float):
    """example_fn(key, spec, perturb_prob) vmapped over the same share of training-stream keys
    for every task spec (batch_size a multiple of len(specs)), concatenated in spec order."""
    if batch_size % len(specs):
        raise ValueError(f"batch size {batch_size} is not a multiple of the {len(specs)} "
                         "task specs")
    keys = training_episode_keys(key, batch_size).reshape(len(specs), -1, 2)
    share = keys.shape[1]
    # A spec listed several times is traced once, over all its shares' keys (the default Kuka
    # recipe lists 8 specs in 16 shares: half the program to compile, the same examples).
    parts = {}
    for spec in dict.fromkeys(specs):
        shares = [i for i, s in enumerate(specs) if s == spec]
        out = jax.vmap(example_fn, in_axes=(0, None, None))(
            keys[np.array(shares)].reshape(-1, 2), spec, perturb_prob)
        for j, i in enumerate(shares):
            parts[i] = jax.tree.map(lambda x, j=j: x[j * share:(j + 1) * share], out)
    return jax.tree.map(lambda *xs: jnp.concatenate(xs), *(parts[i] for i in range(len(specs))))


def as_task_spec(spec) -> TaskSpec:
    """A TaskSpec, or its fields (kind, multi, language) as a sequence (JSON's lists), as one
    (a language name recorded before a rename read as today's: grammar.current_language).
    Raises ValueError naming anything else."""
    if isinstance(spec, TaskSpec):
        return spec
    if (isinstance(spec, (tuple, list)) and len(spec) == 3 and isinstance(spec[0], str)
            and isinstance(spec[1], bool) and isinstance(spec[2], str)):
        return TaskSpec(spec[0], spec[1], grammar.current_language(spec[2]))
    raise ValueError(f"a task spec is a TaskSpec or [kind, multi, language] such as "
                     f"[\"rearrangement\", true, \"paraphrased\"], got {spec!r}")


@dataclasses.dataclass(frozen=True)
class Recipe:
    """The Kuka world's training-data recipe (what the Kuka CLIs' --train uses).

    specs: the task specs (default :data:`DENOISER_SPECS`), each with the same share of every
    batch (the batch size must be a multiple of their number); a spec may also be given as its
    fields ``(kind, multi, language)``, as checkpoints record it (what ``bench_train --set
    specs=[[...], ...]`` passes); list a spec twice to give it twice the share.
    perturb_prob: the share of examples whose moved blocks are perturbed. goal_loss_weight:
    the weight of the goal and pick channels in the loss relative to the path channel's.
    role_loss_weight: 0, or the weight of an auxiliary loss (``diffplan.losses.token_loss``)
    that asks the denoiser's token head which block each block word of a relation names, the
    upper or the lower (``grammar.token_roles``); it needs a denoiser with ``token_classes=2``
    and token ids (refused with text "pretrained": its labels are per token id, and the
    pretrained features have wordpieces, not the grammar's tokens).
    text: "tokens" (the grammar's token ids) or "pretrained" (the frozen pretrained text
    encoder's features of each sentence, ``diffplan.instruction``: the batches carry sentence
    ids into :meth:`sentences`, the training sentence table of the training phrasings only).
    """

    specs: tuple = DENOISER_SPECS
    perturb_prob: float = 0.5
    goal_loss_weight: float = 3.0
    role_loss_weight: float = 0.0
    text: str = "tokens"

    def __post_init__(self):
        check_text(self.text, role_loss_weight=self.role_loss_weight)
        if not 0 <= self.perturb_prob <= 1:
            raise ValueError(f"perturb_prob must be in [0, 1], got {self.perturb_prob}")
        if not self.goal_loss_weight > 0:
            raise ValueError(f"goal_loss_weight must be > 0, got {self.goal_loss_weight}")
        if not self.role_loss_weight >= 0:
            raise ValueError(f"role_loss_weight must be >= 0, got {self.role_loss_weight}")
        object.__setattr__(self, "specs", tuple(map(as_task_spec, self.specs)))
        if not self.specs:
            raise ValueError("specs must name at least one task spec")
        for spec in self.specs:
            check_training_language(spec.language, grammar.LANGUAGES)

    def batch_fn(self):
        """batch_fn(key, batch_size) -> diffplan.train.Batch (text "pretrained": its tokens
        are sentence ids int32 (B, S) of :meth:`sentences`)."""
        from diffplan.losses import with_token_labels
        from diffplan.train import Batch

        specs, prob, weight = self.specs, self.perturb_prob, self.goal_loss_weight
        role_weight = self.role_loss_weight

        def mask(x0):
            return jnp.broadcast_to(jnp.array([1.0, weight, weight], jnp.float32),
                                    x0.shape[:-1] + (NUM_GEN_CHANNELS,))

        def batch_fn(key, batch_size):
            x0, tokens, roles, named = spec_examples(training_example, key, batch_size, specs,
                                                     prob)
            return with_token_labels(Batch(x0=x0, tokens=tokens, loss_mask=mask(x0)), roles,
                                     named, role_weight)

        def sentence_batch_fn(key, batch_size):
            x0, ids = spec_examples(sentence_example, key, batch_size, specs, prob)
            return Batch(x0=x0, tokens=ids, loss_mask=mask(x0))

        return sentence_batch_fn if self.text == "pretrained" else batch_fn

    @property
    def batch_multiple(self) -> int:
        """A batch size must be a multiple of this: the number of specs."""
        return len(self.specs)

    def init_batch(self):
        """Shapes of one batch of batch_multiple (one per spec) examples."""
        return jax.eval_shape(lambda k: self.batch_fn()(k, self.batch_multiple),
                              jax.random.PRNGKey(0))

    def sentences(self):
        """The training sentence table the batches' sentence ids index
        (``envs.kuka.sentences.training_table``; computed once, then read from the disk
        cache), or None with text "tokens"."""
        return training_table() if self.text == "pretrained" else None

    def fixed_params(self, model_config) -> dict | None:
        """The model's constants written before training: for a denoiser that embeds cells by
        their names (``DenoiserConfig.cell_context``), the encoder's features of the block
        colours' names, and with ``standardize`` the training sentences' feature statistics
        (``diffplan.instruction.fixed_text_params``); else None."""
        from diffplan.instruction import fixed_text_params

        return fixed_text_params(model_config, grammar.CELL_TOKENS, instruction_encoder,
                                 self.sentences)

    def metadata(self) -> dict:
        """What a checkpoint records of the recipe (compared when resuming): with text
        "pretrained" the text encoder and the cell tokens instead of the vocabulary
        (``diffplan.instruction.text_metadata``)."""
        meta = {"specs": [[s.kind, s.multi, s.language] for s in self.specs],
                "perturb_prob": self.perturb_prob, "goal_loss_weight": self.goal_loss_weight,
                "num_gen_channels": NUM_GEN_CHANNELS,
                **text_metadata(self.text, grammar.VOCAB, grammar.CELL_TOKENS,
                                instruction_encoder)}
        if self.role_loss_weight:  # absent at 0, as in checkpoints from before it
            meta["role_loss_weight"] = self.role_loss_weight
        return meta
