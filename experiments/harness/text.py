"""The experiment CLIs' instruction input, whatever the world: a checkpoint reads token ids of
the world's vocabulary, or (``DenoiserConfig.context_dim`` > 0, ``--train --text pretrained``)
a frozen pretrained text encoder's features of the instruction's text, computed once per
episode on the host before the rollout (``envs.<world>.sentences.with_features``) with the
encoder the checkpoint recorded (its files' sha256 checked). A user error ends in one line
(exit 2)."""
from __future__ import annotations

from experiments.harness import core as harness


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


def input_mismatch(checkpoint: str, denoiser, vocabulary, cell_tokens) -> str | None:
    """Why a checkpoint cannot read a world's instructions (None if it can): a token-id
    checkpoint trained on another ``vocabulary`` (``core.vocabulary_mismatch``), or a
    features checkpoint whose grid embedding indexes other ``cell_tokens`` than the world's
    condition channel holds (its metadata's ``extra.cell_tokens``)."""
    from diffplan.checkpoint import read_metadata, resolve_checkpoint

    meta = read_metadata(resolve_checkpoint(checkpoint))
    if reads_features(denoiser):
        meta, vocabulary = {"extra": {"vocabulary": meta["extra"].get("cell_tokens")}}, cell_tokens
    return harness.vocabulary_mismatch(meta, denoiser.model_config.vocab_size, vocabulary)


def fill_features(fill, episodes, *args, **kwargs):
    """``fill(episodes, *args, **kwargs)`` (a world's ``sentences.with_features``), a refused
    instruction (empty, or over the encoder's L) ending the program in one line."""
    try:
        return fill(episodes, *args, **kwargs)
    except ValueError as e:
        harness.fail(str(e))
