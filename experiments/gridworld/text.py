"""The grid-world CLIs' instruction input: a checkpoint reads token ids of the grammar's
vocabulary, or (``DenoiserConfig.context_dim`` > 0, ``--train --text pretrained``) a frozen
pretrained text encoder's features of the instruction's text, computed once per episode on
the host before the rollout (``envs.gridworld.sentences.with_features``) with the encoder the
checkpoint recorded (its files' sha256 checked; reads_features, checkpoint_encoder and
check_languages are experiments.harness.text's, shared with the Kuka CLIs)."""
from __future__ import annotations

from experiments.gridworld.spec import LANGUAGE_CHOICES
from experiments.harness.text import (check_languages, checkpoint_encoder,  # noqa: F401
                                      fill_features, reads_features)


def languages_of(choice: str, features: bool) -> tuple[str, ...]:
    """The languages of a --language choice. "all" is the phrasings that may be looked at
    (canonical, paraphrased, unseen) and never the sealed natural-language set: that set is
    measured once, at the end, and only when named (``--language natural``, a checkpoint on
    pretrained features); an "all" on the validation seed must not show it. ``features``
    (the checkpoint reads pretrained features) is kept for the callers' symmetry."""
    del features
    return LANGUAGE_CHOICES[choice]


def with_features(episodes, setting: str, encoder, **slots):
    """The episodes (numpy) with their instructions' features when encoder is given (a
    features checkpoint), else as they are; slots: reference_class / direction to write
    instead of the episodes' own (``envs.gridworld.sentences.episode_texts``)."""
    if encoder is None:
        return episodes
    from envs.gridworld.sentences import with_features as fill

    return fill_features(fill, episodes, setting, encoder, **slots)


def texts(episodes, setting: str) -> list[str]:
    """The episodes' instructions as text (their phrasing and slots, any language)."""
    from envs.gridworld.sentences import episode_texts

    return episode_texts(episodes, setting)
