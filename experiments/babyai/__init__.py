"""The BabyAI levels' experiments (``python -m experiments.babyai``): spec, eval, tables,
flags, cli, baselines, demos (the sample-efficiency sweep) and figures, over ``harness/``."""
