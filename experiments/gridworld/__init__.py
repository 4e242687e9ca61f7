"""The grid world's experiments: what a setting fixes (``spec``), its evaluation (``eval``), its
flags, the CLIs' ``main`` (``cli``), figures, the baselines' and reference agents' rows
(``baselines`` over ``policy_eval``) and the paper's ablation (``ablation``)."""
