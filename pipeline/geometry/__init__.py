"""Two-view geometry: the relative pose of every matched pair and its rotation precision ``H_ij``.

Pure kernels (functions on arrays, no I/O):

- :mod:`pipeline.geometry.epipolar`: normalized coordinates, the essential
  matrix, Sampson distances, triangulation depths, rotation-only fits;
- :mod:`pipeline.geometry.ransac`: 5-point RANSAC with cheirality, refinement and
  degeneracy flags for one pair (:func:`~pipeline.geometry.ransac.estimate_pair`);
- :mod:`pipeline.geometry.ba_model`: the two-view bundle-adjustment model, its
  residuals and Jacobians;
- :mod:`pipeline.geometry.ba_hessian`: the normal equations, the Schur
  elimination of the points and of the translation (``H_ij``);
- :mod:`pipeline.geometry.ba_lm`: robust losses and Levenberg–Marquardt;
- :mod:`pipeline.geometry.ba_solver`: the BA of one pair
  (:func:`~pipeline.geometry.ba_solver.refine_pair`).

Stages (load, call the kernels per pair, save; resumable per pair):

- :mod:`pipeline.geometry.two_view_stage`: ``python -m pipeline.two_view``;
- :mod:`pipeline.geometry.ba_stage`: ``python -m pipeline.two_view_ba``.

Convention (DESIGN.md): ``R_ij = R_j R_iᵀ`` is pycolmap's
``cam2_from_cam1`` rotation, ``x_j = R_ij x_i + t_ij`` with unit ``t_ij``; ``H_ij``
is the precision (1/rad²) of ``Δω`` in ``R_true = exp([Δω]×) R̂_ij``.
"""
