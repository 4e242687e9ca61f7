"""The programs: ``python -m experiments.NAME`` for each entry point at this level, a few lines
that call a ``main`` of one subpackage: ``harness`` (shared by all), ``gridworld`` and ``kuka``
(each world's evaluation, under the same file names), ``sweeping``, ``bench``, ``shipping``.
docs/DESIGN.md, "experiments/ (the programs)", has the table."""
