"""HELIOS object layer (paper section 3.1.3, appendix 6.1): sparse 3D Gaussians for detected task objects with
Dirichlet class beliefs, information gain and the uncertainty-weighted object score.

One module per idea, pure torch (CPU here, CUDA when present, the same code):

* :mod:`.config` -- every knob (Table 3 defaults and the implementation's own, documented).
* :mod:`.gaussians` -- the Gaussian store, creation from the depth error inside detection masks, the bound.
* :mod:`.splat` -- the alpha-blending splat renderer (Eq. 1).
* :mod:`.reobserve` -- the re-observation mask (appendix "Re-observing previously detected parts").
* :mod:`.dirichlet` -- the concentration update (Eq. 3), E and Var (Eq. 4), entropy (Eq. 5).
* :mod:`.info_gain` -- information gain (Eq. 6), optimistic IG (Eq. 12) and Psi' (Eq. 11).
* :mod:`.instances` -- voxel clustering of Gaussians into instances with min-propagated labels.
* :mod:`.scores` -- per-instance class, S_c, U_c and Psi_c (Eq. 7).
* :mod:`.layer` -- one frame's update in order, and the snapshot of the layer.
"""
