"""The Kuka CLIs' instruction input: a checkpoint reads token ids of the grammar's vocabulary,
or (``DenoiserConfig.context_dim`` > 0, ``--train --text pretrained``) a frozen pretrained text
encoder's features of the instruction's text, computed once per episode on the host before the
rollout (``envs.kuka.sentences.with_features``) with the encoder the checkpoint recorded
(``experiments.harness.text.checkpoint_encoder``: its files' sha256 checked)."""
from __future__ import annotations

from experiments.harness import core as harness
from experiments.harness.text import check_languages, checkpoint_encoder, fill_features
from experiments.kuka.spec import LANGUAGE_CHOICES


def languages_of(choice: str) -> tuple[str, ...]:
    """The languages of a --language choice. "all" is the phrasings that may be looked at
    (canonical, paraphrased, development, heldout) and never the sealed natural-language set:
    that set is measured once, at the end, and only when named (``--language natural``, a
    checkpoint on pretrained features); an "all" on the validation seed must not show it."""
    return LANGUAGE_CHOICES[choice]


def checkpoint_input(checkpoint: str, denoiser, languages, reader):
    """The ``diffplan.instruction.InstructionEncoder`` the checkpoint reads instructions with
    (None: token ids; ``experiments.harness.text.checkpoint_encoder``); one line (exit 2) for
    the natural-language set with a token-id checkpoint, and for --reader (which restates
    token ids) with a features one."""
    encoder = checkpoint_encoder(checkpoint, denoiser)
    check_languages(languages, encoder, checkpoint)
    if reader and encoder is not None:
        harness.fail(f"--reader restates an instruction's token ids, and the checkpoint "
                     f"{checkpoint} reads pretrained text features: leave --reader out")
    return encoder


def task_input(encoder) -> str:
    """``KukaTask.text`` for a checkpoint read with encoder (None: token ids)."""
    return "tokens" if encoder is None else "features"


def with_features(episodes, encoder):
    """The episodes (numpy) with their instructions' features when encoder is given (a
    features checkpoint), else as they are; an instruction the encoder refuses ends the
    program in one line."""
    if encoder is None:
        return episodes
    from envs.kuka.sentences import with_features as fill

    return fill_features(fill, episodes, encoder)


def texts(episodes) -> list[str]:
    """The episodes' instructions as text (their phrasings and constraints, any language)."""
    from envs.kuka.sentences import episode_texts

    return episode_texts(episodes)
