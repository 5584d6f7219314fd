"""ASTM E3097 characterization of constant-force thermal cycling (``smabench characterize``).

- :mod:`smabench.characterize.e3097`: cycles and the tangent-line construction (pure numpy);
- :mod:`smabench.characterize.run`: sessions → JSON document, phase diagram, local processes or
  a Dask cluster (one session is one task);
- :mod:`smabench.characterize.report`: PNGs (property evolution, tangents, phase diagram);
- :mod:`smabench.characterize.cli`: the commands ``characterize`` and ``bench characterize``.
"""
