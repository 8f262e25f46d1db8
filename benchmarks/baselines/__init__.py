"""Baseline intrinsic-image methods that mvintrinsic is compared against (not part of the package).

* :mod:`retinex` -- the colour Retinex of Grosse et al. (ICCV 2009); ``run_retinex.py`` runs it on a
  scene folder and writes a result folder that ``benchmarks/evaluate.py`` scores.
"""
