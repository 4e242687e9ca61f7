"""The Kuka world's experiments, under the grid world's file names: ``spec``, ``eval``, ``flags``,
``cli``, ``figures``, ``baselines`` (the baselines acting in physics); and its reader
(``reader``, training it) and the text-only role probe (``role_probe``)."""
