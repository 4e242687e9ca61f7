"""What fills ``checkpoints/``: a denoiser's training run exported with its NOTE.md
(``denoiser``), the baselines' training (``train_baselines``) and their export (``baselines``)."""
