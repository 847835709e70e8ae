"""Every knob of the object layer. Paper values (Table 3, appendix 6.1) are marked; the rest are this
implementation's choices, each explained where it is used."""

from __future__ import annotations

from dataclasses import dataclass

OTHER = "other"  # the class of a pixel no task-class detection covers (evidence *against* every task class)


@dataclass(frozen=True)
class ObjectLayerConfig:
    # --- paper (Table 3 / appendix 6.1) ---
    alpha_cpa: float = 3.0  # concentration update scaling (each observation counts alpha_cpa times)
    alpha_cs: float = 1.0  # weight of U_c in Psi_c = S_c - alpha_cs U_c (Eq. 7)
    reobserve_depth_m: float = 0.5  # re-observation: measured depth within this of the rendered depth
    voxel_m: float = 0.5  # instance clustering voxel size
    new_depth_error_m: float = 1.0  # creation: depth error above this where the layer renders something
    new_empty_error_m: float = 0.001  # creation: depth error above this where the layer renders nothing
    # --- this implementation ---
    prior: float = 1.0  # initial concentration of every class (a uniform Dirichlet)
    render_scale: float = 0.5  # the update works at this fraction of the frame's resolution (640x480 -> 320x240)
    spawn_stride_px: int = 4  # one new Gaussian per stride x stride block of the (scaled) detection mask
    erosion_px: int = 1  # erosion of each class mask before creation (bleeding mask edges make no Gaussians)
    close_px: int = 2  # radius of the morphological closing of the re-observation mask
    init_opacity: float = 0.8  # opacity of a new Gaussian (fixed: nothing is trained)
    scale_factor: float = 0.4  # sigma of a new Gaussian = this x its spawn block's footprint in metres
    max_splat_radius_px: int = 8  # splats are cut at 3 sigma or this radius (scaled image pixels)
    min_alpha: float = 1.0 / 255.0  # 3DGS: contributions below this are skipped
    max_alpha: float = 0.99  # 3DGS: alpha clamp
    min_transmittance: float = 1e-4  # 3DGS: stop blending behind this
    valid_acc: float = 0.5  # rendered depth is defined where the accumulated alpha reaches this
    max_depth_m: float = 8.0  # measured depth past this is not used (noisy, far objects)
    # "other" pixels (no detection) past this depth are no evidence (None: up to max_depth_m). A missed detection
    # is evidence against an object only where the detector would see it: see ObjectMapConfig.miss_range_m.
    other_max_depth_m: float | None = None
    touched_evidence: float = 0.05  # a Gaussian counts as updated by a frame when it got this much evidence
    max_gaussians: int = 60_000  # the bound; see gaussians.GaussianStore.enforce_bound for the drop policy
    max_new_per_frame: int = 6_000  # creations of one frame beyond this are dropped (farthest first)
    max_instances: int = 256  # instances published per update (highest task-class score first)
    gaze_width: int = 96  # optimistic renders (Eq. 11, 12) at this width (height by the frame's aspect)

    def __post_init__(self) -> None:
        if not 0.05 <= self.render_scale <= 1.0:
            raise ValueError(f"render_scale must be in [0.05, 1], got {self.render_scale}")
        if self.spawn_stride_px < 1 or self.max_splat_radius_px < 1:
            raise ValueError("spawn_stride_px and max_splat_radius_px must be >= 1")
        if self.max_gaussians < 1 or self.max_new_per_frame < 0:
            raise ValueError("max_gaussians must be >= 1 and max_new_per_frame >= 0")
        if self.prior <= 0 or self.alpha_cpa <= 0:
            raise ValueError("prior and alpha_cpa must be > 0 (Dirichlet concentrations stay positive)")
        if not 0.0 < self.init_opacity <= self.max_alpha:
            raise ValueError(f"init_opacity must be in (0, {self.max_alpha}]")

    @property
    def pixel_weight(self) -> float:
        """Weight of one pixel's kappa in Eq. 3 at the update resolution.

        The paper creates one Gaussian per detected pixel, so a Gaussian seen again gets about one pixel's
        worth of kappa per view. Here one Gaussian stands for a ``spawn_stride_px``^2 block, so each pixel's
        kappa counts 1/stride^2: a Gaussian seen from about where it was created gets on average about
        ``alpha_cpa`` evidence per view, whatever the stride and resolution."""
        return 1.0 / float(self.spawn_stride_px**2)
