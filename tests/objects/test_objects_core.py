"""HELIOS object layer core (services/mapper/objects): each equation against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import special, stats

from services.mapper.objects import dirichlet, splat
from services.mapper.objects.config import ObjectLayerConfig
from services.mapper.objects.gaussians import GaussianStore
from services.mapper.objects.info_gain import information_gain
from services.mapper.objects.instances import components, relabel
from services.mapper.objects.layer import ObjectLayer, camera_from_gaze
from services.mapper.objects.reobserve import close, reobservation_mask
from services.mapper.objects.scores import class_scores, instance_class

W, H = 160, 120
F = W / 2 / math.tan(math.radians(60))
K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])
EYE = np.eye(4)


# ---- Eq. 1 ---------------------------------------------------------------------------------------------
def test_splat_single_gaussian_centre_kappa_is_its_opacity() -> None:
    Kt = torch.tensor(K, dtype=torch.float32)
    # a Gaussian on the optical axis 2 m ahead projects to the principal point (79.5, 59.5): put it on a pixel
    u, v = 80.0, 60.0
    x, y = (u - K[0, 2]) / F * 2.0, (v - K[1, 2]) / F * 2.0
    r = splat.render(torch.tensor([[x, y, 2.0]]), torch.tensor([0.02]), torch.tensor([0.7]), torch.eye(4), Kt, H, W)
    centre = 60 * W + 80
    k = r.kappa[r.pixel == centre]
    assert k.numel() == 1 and float(k) == pytest.approx(0.7, abs=1e-6)
    assert float(r.depth[60, 80]) == pytest.approx(2.0, abs=1e-5)
    # a neighbour pixel: alpha * exp(-1/2 d^2 / s2) with s2 = (f sigma / z)^2 + 0.3 (x, y are ~0: J ~ diag)
    s2 = (F * 0.02 / 2.0) ** 2 + splat.EWA_DILATION
    k1 = float(r.kappa[r.pixel == centre + 1])
    assert k1 == pytest.approx(0.7 * math.exp(-0.5 / s2), rel=1e-3)


def test_splat_front_to_back_blending() -> None:
    """Two Gaussians on one pixel: kappa_1 = a1, kappa_2 = a2 (1 - a1) whatever their order in memory."""
    Kt = torch.tensor(K, dtype=torch.float32)
    x, y = (80 - K[0, 2]) / F, (60 - K[1, 2]) / F
    means = torch.tensor([[x * 3, y * 3, 3.0], [x * 2, y * 2, 2.0]])  # the far one first
    r = splat.render(means, torch.tensor([0.01, 0.01]), torch.tensor([0.6, 0.5]), torch.eye(4), Kt, H, W)
    centre = 60 * W + 80
    at = {int(g): float(k) for g, k in zip(r.gauss[r.pixel == centre], r.kappa[r.pixel == centre], strict=True)}
    assert at[1] == pytest.approx(0.5, abs=1e-6)  # near
    assert at[0] == pytest.approx(0.6 * 0.5, abs=1e-6)  # far, behind the near one
    assert float(r.acc[60, 80]) == pytest.approx(0.8, abs=1e-6)
    assert float(r.depth[60, 80]) == pytest.approx((0.5 * 2 + 0.3 * 3) / 0.8, abs=1e-4)
    assert float(r.acc.max()) <= 1.0 + 1e-6


# ---- Eq. 3-5 -------------------------------------------------------------------------------------------
def test_dirichlet_update_closed_form() -> None:
    gamma = torch.ones(2, 3)
    gauss = torch.tensor([0, 0, 1, 1])
    kappa = torch.tensor([0.5, 0.25, 1.0, 0.1])
    cls = torch.tensor([0, 2, 1, 1])
    out = dirichlet.update(gamma, gauss, kappa, cls, alpha_cpa=3.0, pixel_weight=0.5)
    expected = torch.tensor([[1 + 3 * 0.5 * 0.5, 1, 1 + 3 * 0.5 * 0.25], [1, 1 + 3 * 0.5 * 1.1, 1]])
    assert torch.allclose(out, expected)
    assert torch.equal(gamma, torch.ones(2, 3))  # a new tensor


def test_expectation_variance_closed_form() -> None:
    g = torch.tensor([[2.0, 1.0, 1.0]], dtype=torch.float64)
    assert torch.allclose(dirichlet.expectation(g), torch.tensor([[0.5, 0.25, 0.25]], dtype=torch.float64))
    # Var = E (1 - E) / (1 + T), T = 4
    want = torch.tensor([[0.25 / 5, 0.1875 / 5, 0.1875 / 5]], dtype=torch.float64)
    assert torch.allclose(dirichlet.variance(g), want)


def test_entropy_closed_forms() -> None:
    assert float(dirichlet.entropy(torch.ones(1, 2, dtype=torch.float64))) == pytest.approx(0.0, abs=1e-12)
    # uniform Dirichlet on the simplex of C classes: -log((C-1)!)... H = log B(1..1) = -log Gamma(C)
    assert float(dirichlet.entropy(torch.ones(1, 4, dtype=torch.float64))) == pytest.approx(-math.log(6), abs=1e-12)
    # Beta(2, 1): ln B = ln(1/2); H = ln(1/2) + (3 - 2) psi(3) - (2 - 1) psi(2)
    h = math.log(0.5) + special.digamma(3) - special.digamma(2)
    assert float(dirichlet.entropy(torch.tensor([[2.0, 1.0]], dtype=torch.float64))) == pytest.approx(h, abs=1e-12)
    rng = np.random.default_rng(0)
    for _ in range(20):
        a = rng.uniform(0.3, 30.0, size=rng.integers(2, 6))
        got = float(dirichlet.entropy(torch.tensor(a[None], dtype=torch.float64)))
        assert got == pytest.approx(stats.dirichlet(a).entropy(), abs=1e-9)


def test_information_gain_non_negative_for_confirming_evidence() -> None:
    """Eq. 6: evidence for the most likely class (what Eq. 12's optimistic views add) never raises H."""
    rng = np.random.default_rng(1)
    for _ in range(200):
        g = torch.tensor(rng.uniform(0.5, 20.0, size=(1, 4)), dtype=torch.float64)
        after = g.clone()
        after[0, int(g.argmax())] += rng.uniform(0.01, 10.0)
        assert float(information_gain(g, after)) >= -1e-12
        scaled = g * rng.uniform(1.0, 5.0)  # same expectation, more evidence
        assert float(information_gain(g, scaled)) >= -1e-12


def test_psi_bounds() -> None:
    """Eq. 7: -alpha_cs / 2 <= Psi_c <= S_c <= 1, U_c in [0, 1/2]."""
    rng = np.random.default_rng(2)
    for alpha_cs in (0.0, 1.0, 2.5):
        for _ in range(50):
            g = torch.tensor(rng.uniform(0.01, 50.0, size=(rng.integers(1, 30), 3)))
            s, u, psi = class_scores(g, alpha_cs)
            assert bool((u >= 0).all() and (u <= 0.5).all())
            assert bool((psi <= s + 1e-12).all() and (s <= 1).all() and (psi >= -alpha_cs / 2 - 1e-12).all())
    # hand value: one Gaussian (3, 1): E = .75, Var = .75 * .25 / 5, Psi = .75 - sqrt(.0375)
    s, u, psi = class_scores(torch.tensor([[3.0, 1.0]], dtype=torch.float64), 1.0)
    assert float(psi[0]) == pytest.approx(0.75 - math.sqrt(0.0375), abs=1e-12)
    assert instance_class(torch.tensor([[3.0, 1.0], [1.0, 2.0], [5.0, 1.0]])) == 0  # mode of argmax


# ---- re-observation mask --------------------------------------------------------------------------------
def test_reobservation_mask() -> None:
    measured = torch.full((9, 9), 3.0)
    rendered = torch.full((9, 9), 2.8)
    rendered[:, :3] = 0.0  # nothing rendered there
    measured[:, 6:] = 1.0  # an occluder 1.8 m in front of the layer
    rendered[4, 4] = 0.0  # a one-pixel hole: closed
    m = reobservation_mask(measured, rendered, 0.5, close_px=1)
    assert bool(m[4, 4]) and bool(m[:, 3:6].all())
    assert not bool(m[:, 7:].any()) and not bool(m[:, :2].any())
    assert bool(close(torch.tensor([[1, 0, 1]], dtype=torch.bool), 1).all())


# ---- instances ------------------------------------------------------------------------------------------
def test_components_26_connectivity() -> None:
    pts = np.array([[0.1, 0.1, 0.1], [0.6, 0.6, 0.6], [1.6, 1.6, 1.6], [1.1, 0.1, 0.1]])
    comp = components(pts, 0.5)
    assert comp[0] == comp[1]  # corner neighbours (26-connected)
    assert comp[1] == comp[3]  # voxel (2,0,0) touches (1,1,1) by a corner
    assert comp[2] != comp[0]  # (3,3,3) is two voxels away


def test_relabel_min_propagation_split_and_new() -> None:
    means = np.array([[0.1, 0, 0], [0.6, 0, 0], [5.0, 0, 0], [5.2, 0, 0], [9.0, 0, 0]])
    cls = np.zeros(5, dtype=np.int64)
    prev = np.array([4, 2, 2, 2, -1])
    new, nxt = relabel(means, cls, prev, np.arange(5), next_label=7)
    # cluster {0,1} had labels {4,2} -> 2 (the minimum); {2,3} had {2} but 2 is taken by... the larger cluster
    # first: both have 2 Gaussians, ties by lowest index -> {0,1} takes 2; {2,3} gets a new label 7; {4} -> 8
    assert new.tolist() == [2, 2, 7, 7, 8] and nxt == 9
    # the same Gaussians again: labels unchanged (stable across frames)
    again, nxt2 = relabel(means, cls, new, np.arange(5), next_label=nxt)
    assert again.tolist() == new.tolist() and nxt2 == nxt


# ---- the layer ------------------------------------------------------------------------------------------
def _scene(object_depth: float = 2.5) -> tuple[np.ndarray, np.ndarray]:
    depth = np.full((H, W), 3.0, np.float32)
    depth[40:80, 60:100] = object_depth
    cls = np.full((H, W), 2, np.int64)
    cls[40:80, 60:100] = 0
    return depth, cls


def test_layer_fuses_views_and_keeps_instance_labels() -> None:
    cfg = ObjectLayerConfig(render_scale=1.0)
    layer = ObjectLayer(["mug", "table"], cfg)
    depth, cls = _scene()
    s1 = layer.update(depth, cls, EYE, K, 0)
    assert s1.created > 0 and s1.gaussians == s1.created
    inst = layer.instances()
    assert len(inst) == 1 and layer.classes[inst[0].cls] == "mug"
    label = inst[0].instance_id
    # only the detected object got Gaussians, at the measured depth
    assert torch.allclose(layer.store.means[:, 2], torch.tensor(2.5), atol=1e-4)
    s2 = layer.update(depth, cls, EYE, K, 1)
    assert s2.created == 0  # re-observed, nothing new
    after = layer.instances()
    assert [i.instance_id for i in after] == [label]
    assert after[0].S[0] > inst[0].S[0] and after[0].psi[0] > inst[0].psi[0] and after[0].U[0] < inst[0].U[0]
    # the object not detected from the same place: evidence for "other"; S_mug falls
    layer.update(depth, np.full((H, W), 2, np.int64), EYE, K, 2)
    third = {i.instance_id: i for i in layer.instances()}
    assert label in third and third[label].S[0] < after[0].S[0]


def test_occluded_gaussians_are_not_updated() -> None:
    layer = ObjectLayer(["mug"], ObjectLayerConfig(render_scale=1.0))
    depth, cls = _scene()
    cls[cls == 2] = 1
    cls[cls == 0] = 0
    layer.update(depth, cls, EYE, K, 0)
    before = layer.store.gamma.clone()
    occluded = depth.copy()
    occluded[:, :] = 1.0  # a wall 1.5 m in front of the object, nothing detected
    layer.update(occluded, np.full((H, W), 1, np.int64), EYE, K, 1)
    assert torch.equal(layer.store.gamma, before)


def test_bound_drops_oldest_first() -> None:
    st = GaussianStore.empty(2)
    for step in range(3):
        st.append(
            GaussianStore(
                torch.zeros(2, 3), torch.ones(2), torch.ones(2), torch.ones(2, 2) * (step + 1),
                torch.full((2,), -1), torch.full((2,), step),
            )
        )
    assert st.enforce_bound(4) == 2
    assert sorted(st.last_step.tolist()) == [1, 1, 2, 2]
    layer = ObjectLayer(["mug"], ObjectLayerConfig(render_scale=1.0, max_gaussians=10, max_new_per_frame=5))
    depth, cls = _scene()
    cls[cls == 2] = 1
    stats = layer.update(depth, cls, EYE, K, 0)
    assert stats.created == 5 and len(layer.store) == 5


def test_optimistic_ig_and_psi_prime() -> None:
    layer = ObjectLayer(["mug", "table"], ObjectLayerConfig(render_scale=1.0))
    depth, cls = _scene()
    layer.update(depth, cls, EYE, K, 0)
    inst = layer.instances()[0]
    pose = torch.tensor(EYE, dtype=torch.float32)
    opt = layer.optimistic(inst.instance_id, 0, [pose, pose], width=W)
    assert opt.pixels > 0 and opt.ig > 0  # Eq. 12 >= 0 for the believed class
    assert opt.psi_prime > inst.psi[0]  # Eq. 11: two more confirming views raise Psi
    far = camera_from_gaze(0.0, 0.0, math.pi / 2, 0.0, 0.0)  # looking away: nothing to see
    none = layer.optimistic(inst.instance_id, 0, [far], width=W)
    assert none.pixels == 0 and none.ig == pytest.approx(0.0, abs=1e-9)
    assert none.psi_prime == pytest.approx(inst.psi[0], abs=1e-6)


def test_snapshot_restore_round_trip() -> None:
    layer = ObjectLayer(["mug", "table"], ObjectLayerConfig(render_scale=1.0))
    depth, cls = _scene()
    layer.update(depth, cls, EYE, K, 0)
    back = ObjectLayer.restore(layer.snapshot(), layer.config)
    assert back.classes == layer.classes and back.next_label == layer.next_label
    assert torch.equal(back.store.gamma, layer.store.gamma) and torch.equal(back.store.instance, layer.store.instance)
    a = layer.update(depth, cls, EYE, K, 1)
    b = back.update(depth, cls, EYE, K, 1)
    assert a.gaussians == b.gaussians and torch.allclose(back.store.gamma, layer.store.gamma)


def test_bad_input() -> None:
    with pytest.raises(ValueError, match="classes"):
        ObjectLayer([])
    with pytest.raises(ValueError, match="distinct"):
        ObjectLayer(["mug", "mug"])
    layer = ObjectLayer(["mug"])
    depth, _ = _scene()
    with pytest.raises(ValueError, match="class indices"):
        layer.update(depth, np.full((H, W), 5), EYE, K, 0)
    with pytest.raises(ValueError, match="differ"):
        layer.update(depth, np.zeros((2, 2), np.int64), EYE, K, 0)
