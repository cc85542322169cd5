"""Reconstruction from captures: analytic multiplexed photometric stereo, Woodham least squares,
metrics, and the baseline inverse renderer.

Main entry points (shapes and conventions in each docstring and in DESIGN sections 2-5):
- ``reconstruct.photometric_stereo``: ``solve_ps`` / ``solve_ps_image`` with ``PSConfig`` ->
  ``PSResult`` (differentiable w.r.t. captures and emission);
- ``reconstruct.woodham``: ``solve_woodham``, ``solve_woodham_olat``, ``solve_woodham_image``
  with ``WoodhamConfig`` -> ``PSResult``;
- ``reconstruct.metrics``: ``angular_error_deg``, ``normal_metrics``, ``psnr``, ``ssim``;
- ``reconstruct.reference``: slow per-pixel versions of the solvers, for tests.

Internals: ``lighting`` (effective lighting and moments), ``pixel_solve`` (per-pixel algebra),
``shadow_search`` (attached-shadow search). This package imports ``capture_sim`` only.
"""
