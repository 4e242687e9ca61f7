"""The instruction grammar of the grid world, in one place.

Everything about language lives here: the object classes, the compass directions, the instruction
templates of each setting (several phrasings per meaning, used for the "complex instruction"
study) and the word-level vocabulary built from them.

Templates are written with three slots: ``{ref}`` (the reference object), ``{target}`` and
``{dir}`` (the compass direction from the reference to the target). Each template is compiled
once into an int32 array of token ids in which the slots are negative markers, so that the
JAX episode generator can fill them with ``jnp.where`` (see :func:`fill_template`): instructions
are produced inside ``jit`` as token ids and turned into text only when exported. The
vocabulary, tokenizer and template machinery are the shared ``diffplan.language``.
"""
from __future__ import annotations

import numpy as np

from diffplan import language

OBJECT_NAMES: tuple[str, ...] = (
    "apple", "carrot", "banana", "lettuce", "orange", "tomato", "grapes", "broccoli",
    "strawberry", "cucumber", "pear", "cherry", "onion", "potato", "pepper",
)
"""Object classes; class k (1-based, as stored in the grid) is ``OBJECT_NAMES[k - 1]``."""

DIRECTIONS: tuple[str, ...] = (
    "east", "northeast", "north", "northwest", "west", "southwest", "south", "southeast",
)
"""Compass sectors counter-clockwise from east; sector s covers angles (s*45 - 22.5, s*45 + 22.5]
degrees, with north = row 0 (up)."""

# Special tokens. Ids 1-3 double as cell tokens of the observation's cell-id channel.
PAD, UNSEEN, EMPTY, OBSTACLE = "<pad>", "<unseen>", "<empty>", "<obstacle>"
SPECIAL_TOKENS: tuple[str, ...] = (PAD, UNSEEN, EMPTY, OBSTACLE)
PAD_ID, UNSEEN_ID, EMPTY_ID, OBSTACLE_ID = 0, 1, 2, 3

_GOAL_ONLY = (
    # training: canonical (0) and paraphrases (1-7)
    "Go to the {target}.",
    "Walk to the {target}.",
    "Find the {target}.",
    "Navigate to the {target}.",
    "Head towards the {target}.",
    "Your goal is the {target}.",
    "The {target} is where you should go.",
    "Please move to the {target}.",
    # held out (8-11)
    "Move towards the {target}.",
    "The {target} is your goal.",
    "Please find the {target}.",
    "Go where the {target} is.",
)

_VIA_REFERENCE = (
    # training: canonical (0) and paraphrases (1-7); 6 and 7 name the target first
    "First, go to the {ref}. Then, go {dir} to find the {target}.",
    "First, walk to the {ref}, then head {dir} towards the {target}.",
    "Go to the {ref} first. The {target} is {dir} of it.",
    "Find the {ref}. From there, the {target} lies to the {dir}.",
    "Head towards the {ref}, then go {dir} and find the {target}.",
    "Navigate to the {ref}. Then, search {dir} for the {target}.",
    "The {target} lies {dir} of the {ref}. Go to the {ref} first.",
    "The {target} is to the {dir} of the {ref}. Walk to the {ref}, then find the {target}.",
    # held out (8-11); 9 and 11 name the target first
    "Walk to the {ref}. The {target} is {dir} of the {ref}.",
    "The {target} lies to the {dir} of the {ref}. First, go to the {ref}.",
    "Navigate to the {ref} first, then search {dir} for the {target}.",
    "Find the {target}. It lies {dir} of the {ref}. Go to the {ref} first.",
)

TEMPLATES: dict[str, tuple[str, ...]] = {
    "1o1g": _GOAL_ONLY,
    "mo1g": _GOAL_ONLY,
    "p_mo2g": _VIA_REFERENCE,
    "p_mo2g_far": _VIA_REFERENCE,
}
"""Twelve phrasings of each setting's meaning: template 0 is the canonical phrasing, 1-7 the
training paraphrases, 8-11 the held-out ("unseen") third that training never sees
(:data:`SPLITS`; every word of them occurs in a training phrasing of the same setting).
Settings of one meaning share one table: 1o1g and mo1g "go to the target"; p_mo2g and
p_mo2g_far "go to the reference first, the target lies <dir> of it" (the same token ids, so a
denoiser of one reads the other's instructions)."""

UNSEEN_TEMPLATES = (8, 9, 10, 11)
NUM_TEMPLATES = 12
"""Phrasings per setting in :data:`TEMPLATES`; an episode's ``template`` at or past it indexes
the sealed natural-language set (:func:`all_phrasings`)."""


def phrasings(has_reference: bool) -> tuple[str, ...]:
    """The twelve phrasings (:data:`TEMPLATES`) of the settings with a reference (P-MO2G,
    P-MO2G-far) or without one (1O1G, MO1G): an episode's ``template`` indexes them."""
    return _VIA_REFERENCE if has_reference else _GOAL_ONLY


def all_phrasings(has_reference: bool) -> tuple[str, ...]:
    """What an episode's ``template`` indexes in every language: the twelve phrasings, then
    the sealed natural-language set (``envs.gridworld.natural``, the language "natural":
    templates NUM_TEMPLATES ...), whose slots also include ``{dir_h}`` (the direction
    hyphenated). Their text only: natural sentences have words outside the vocabulary, so
    only a denoiser on pretrained features reads them (their episodes' ``tokens`` hold the
    canonical phrasing of the same meaning, which the slot readers (the baselines' goal
    vector, the searcher) parse)."""
    from envs.gridworld import natural

    return phrasings(has_reference) + natural.sentences(has_reference)


def render_phrasing(phrasing: str, ref_class: int, target_class: int, direction: int) -> str:
    """A phrasing with its slots filled (1-based classes; ref_class 0 and direction -1 where
    the setting has none): {ref}, {target}, {dir} and {dir_h} (hyphenated: "north-east")."""
    from envs.gridworld import natural

    word = DIRECTIONS[direction] if direction >= 0 else ""
    return language.render(phrasing, {
        "ref": OBJECT_NAMES[ref_class - 1] if ref_class > 0 else "",
        "target": OBJECT_NAMES[target_class - 1], "dir": word,
        "dir_h": natural.hyphenated(word)})


SLOT_REF, SLOT_TARGET, SLOT_DIR = -1, -2, -3
_SLOT_NAMES = ("{ref}", "{target}", "{dir}")
"""Slot k of a template is the marker -(k + 1) (diffplan.language's convention)."""

LANGUAGES = language.LANGUAGES
SPLITS: dict[str, language.TemplateSplit] = {
    setting: language.TemplateSplit(templates, UNSEEN_TEMPLATES, _SLOT_NAMES)
    for setting, templates in TEMPLATES.items()}
"""Each setting's phrasings split into canonical, training paraphrases and held-out ones."""


EVALUATION_LANGUAGES = LANGUAGES + (language.NATURAL,)
"""The grid world's evaluation languages: canonical, paraphrased, unseen and the sealed
natural-language set ("natural": read only by denoisers on pretrained features)."""


def template_pool(setting: str, language_name: str) -> np.ndarray:
    """int32 (P,) the template indices an episode of the setting draws its phrasing from
    (diffplan.language.TemplateSplit.pool; "natural": the natural set's sentences, templates
    NUM_TEMPLATES ... of :func:`all_phrasings`)."""
    if setting not in SPLITS:
        raise ValueError(f"unknown setting {setting!r}; expected one of {sorted(SPLITS)}")
    if language_name == language.NATURAL:
        from envs.gridworld import natural

        count = len(natural.sentences(TEMPLATES[setting] is _VIA_REFERENCE))
        return np.arange(NUM_TEMPLATES, NUM_TEMPLATES + count, dtype=np.int32)
    return SPLITS[setting].pool(language_name)


def token_template(template):
    """The template whose tokens an episode carries: its own, or for a natural-language one
    (template >= NUM_TEMPLATES) the canonical template 0. jnp-compatible."""
    import jax.numpy as jnp

    return jnp.where(template < NUM_TEMPLATES, template, 0)


def split_words(text: str) -> list[str]:
    """Lower-cases and splits text into words and punctuation tokens ('.' and ','); any other
    run of characters (digits, '!', ...) becomes a word of its own (outside the vocabulary)."""
    return language.split_words(text)


def _build_vocab() -> tuple[str, ...]:
    words = set(OBJECT_NAMES) | set(DIRECTIONS) | set().union(
        *(split.training_words() for split in SPLITS.values()))
    # Object names first (right after the specials) so that their ids are stable and compact.
    rest = sorted(words - set(OBJECT_NAMES))
    return SPECIAL_TOKENS + OBJECT_NAMES + tuple(rest)


_VOCABULARY = language.Vocabulary(_build_vocab(), num_specials=len(SPECIAL_TOKENS))
VOCAB: tuple[str, ...] = _VOCABULARY.words
WORD_TO_ID: dict[str, int] = _VOCABULARY.word_to_id
OBJECT_TOKEN_OFFSET = len(SPECIAL_TOKENS)
"""Token id of object class k (1-based) is ``k - 1 + OBJECT_TOKEN_OFFSET``."""
CELL_TOKENS: tuple[str, ...] = VOCAB[:OBJECT_TOKEN_OFFSET + len(OBJECT_NAMES)]
"""The tokens a grid cell can hold (condition channel 0): the specials and the object names,
ids 0 .. len - 1 (a denoiser on pretrained text features embeds these only)."""
DIRECTION_TOKEN_IDS = np.array([WORD_TO_ID[d] for d in DIRECTIONS], np.int32)
MAX_TOKENS = 24
"""Fixed instruction length (tokens, padded with 0) of every template, with room to spare."""


def class_to_token(object_class):
    """Token id of an object class (1-based class ids; works on ints, numpy and jax arrays)."""
    return object_class - 1 + OBJECT_TOKEN_OFFSET


def encode(text: str, max_tokens: int = MAX_TOKENS) -> np.ndarray:
    """Word-level tokenizer: text -> int32 (max_tokens,) ids padded with 0.

    Raises ValueError naming every word outside the vocabulary, or if the text is too long.
    """
    return _VOCABULARY.encode(text, max_tokens)


def decode(ids) -> str:
    """int token ids (padding 0 dropped) -> text with punctuation re-attached."""
    return _VOCABULARY.decode(ids)


def compile_templates(setting: str) -> np.ndarray:
    """The setting's templates as int32 (num_templates, MAX_TOKENS) token ids with negative slot
    markers (SLOT_REF, SLOT_TARGET, SLOT_DIR) and 0 padding."""
    if setting not in TEMPLATES:
        raise ValueError(f"unknown setting {setting!r}; expected one of {sorted(TEMPLATES)}")
    return np.stack([_VOCABULARY.compile(t, _SLOT_NAMES, MAX_TOKENS)
                     for t in TEMPLATES[setting]])


def fill_template(template_ids, ref_class, target_class, direction):
    """Fills a compiled template (int32 (L,)) with token ids; jnp-compatible (works in jit).

    Args: ref_class, target_class: 1-based object classes; direction: sector index 0..7.
    Returns int32 (L,) token ids.
    """
    import jax.numpy as jnp

    slot_tokens = jnp.stack([jnp.asarray(class_to_token(ref_class), jnp.int32),
                             jnp.asarray(class_to_token(target_class), jnp.int32),
                             jnp.asarray(DIRECTION_TOKEN_IDS)[direction]])
    return language.fill_slots(template_ids, slot_tokens)


def render(setting: str, template: int, ref_class: int, target_class: int, direction: int) -> str:
    """Plain-Python rendering of an instruction (the reference for tests and export); template
    indexes :func:`all_phrasings` (the natural set's sentences from NUM_TEMPLATES on)."""
    if setting not in TEMPLATES:
        raise ValueError(f"unknown setting {setting!r}; expected one of {sorted(TEMPLATES)}")
    table = (TEMPLATES[setting] if template < NUM_TEMPLATES
             else all_phrasings(TEMPLATES[setting] is _VIA_REFERENCE))
    return render_phrasing(table[template], ref_class, target_class, direction)


def _all_templates():
    """Every distinct table of templates compiled and stacked (int32 (sum N, MAX_TOKENS)) and
    the setting name (the first setting of the table) and template index of each row."""
    rows, names = [], []
    first_setting = {}
    for setting, table in TEMPLATES.items():
        first_setting.setdefault(table, setting)
    for setting in first_setting.values():
        rows.append(compile_templates(setting))
        names += [(setting, i) for i in range(len(TEMPLATES[setting]))]
    return np.concatenate(rows), tuple(names)


_COMPILED, _TEMPLATE_NAMES = _all_templates()


def parse(tokens):
    """(matched, ref_token, target_token, dir_token) of instruction tokens int (MAX_TOKENS,):
    the words in the slots of whichever phrasing (any setting, held-out ones included) the
    instruction is; matched False (and 0 tokens) if it is none of them. jit-able."""
    index, slots = language.match_template(tokens, _COMPILED)
    return index >= 0, slots[0], slots[1], slots[2]


def which_template(tokens) -> tuple[str, int] | None:
    """(setting, template index) of an instruction's tokens (numpy), or None: plain Python,
    for tests and export."""
    index, _ = language.match_template(np.asarray(tokens), _COMPILED)
    index = int(index)
    return None if index < 0 else _TEMPLATE_NAMES[index]
