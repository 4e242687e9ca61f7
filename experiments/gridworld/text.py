"""The grid-world CLIs' instruction input: a checkpoint reads token ids of the grammar's
vocabulary, or (``DenoiserConfig.context_dim`` > 0, ``--train --text pretrained``) a frozen
pretrained text encoder's features of the instruction's text, computed once per episode on
the host before the rollout (``envs.gridworld.sentences.with_features``) with the encoder the
checkpoint recorded (its files' sha256 checked)."""
from __future__ import annotations

from experiments.harness import core as harness
from experiments.gridworld.spec import LANGUAGE_CHOICES


def languages_of(choice: str, features: bool) -> tuple[str, ...]:
    """The languages of a --language choice. "all" is the phrasings that may be looked at
    (canonical, paraphrased, unseen) and never the sealed natural-language set: that set is
    measured once, at the end, and only when named (``--language natural``, a checkpoint on
    pretrained features); an "all" on the validation seed must not show it. ``features``
    (the checkpoint reads pretrained features) is kept for the callers' symmetry."""
    del features
    return LANGUAGE_CHOICES[choice]


def reads_features(denoiser) -> bool:
    """The denoiser reads pretrained text features (not token ids)."""
    return bool(getattr(denoiser.model_config, "context_dim", 0))


def checkpoint_encoder(checkpoint: str, denoiser):
    """The ``diffplan.instruction.InstructionEncoder`` a features checkpoint was trained with
    (None for a token-id checkpoint); one-line error (exit 2) if it cannot be loaded or its
    files differ from the recorded ones."""
    from diffplan.checkpoint import read_metadata, resolve_checkpoint
    from diffplan.instruction import load_instruction_encoder

    if not reads_features(denoiser):
        return None
    record = read_metadata(resolve_checkpoint(checkpoint)).get("extra", {}).get("text_encoder")
    if record is None:
        harness.fail(f"the checkpoint {checkpoint} reads pretrained features but records no "
                     "text encoder")
    try:
        encoder = load_instruction_encoder(record)
    except ValueError as e:
        harness.fail(f"the checkpoint {checkpoint}'s text encoder: {e}")
    if encoder.dim != denoiser.model_config.context_dim:
        harness.fail(f"the checkpoint {checkpoint} reads {denoiser.model_config.context_dim}-wide "
                     f"features, its text encoder gives {encoder.dim}")
    return encoder


def check_languages(languages, encoder, checkpoint: str) -> None:
    """One line (exit 2) for the natural-language set with a token-id checkpoint."""
    if "natural" in languages and encoder is None:
        harness.fail(f"--language natural needs a denoiser on pretrained text features (train "
                     f"one with --train --text pretrained): the checkpoint {checkpoint} reads "
                     f"token ids, and natural sentences have words outside its vocabulary")


def with_features(episodes, setting: str, encoder, **slots):
    """The episodes (numpy) with their instructions' features when encoder is given (a
    features checkpoint), else as they are; slots: reference_class / direction to write
    instead of the episodes' own (``envs.gridworld.sentences.episode_texts``)."""
    if encoder is None:
        return episodes
    from envs.gridworld.sentences import with_features as fill

    try:
        return fill(episodes, setting, encoder, **slots)
    except ValueError as e:
        harness.fail(str(e))


def texts(episodes, setting: str) -> list[str]:
    """The episodes' instructions as text (their phrasing and slots, any language)."""
    from envs.gridworld.sentences import episode_texts

    return episode_texts(episodes, setting)
