"""The harness every experiment shares, whatever the world: seeds, keys and the jitted rollout
(``core``), compiling several programs at once, text tables, intervals, progress bars, the
denoiser recipes and the CLIs' output checks. It imports no world's evaluation module."""
