"""A home's HELIOS object layer across task episodes, without I/O: Gaussians with class evidence keyed by class
name, and the floor a detector asked for each class has explored.

A task episode's layer (:mod:`services.mapper.objects.layer`) holds per Gaussian ``n`` the Dirichlet
concentrations ``gamma_n`` over the task's classes ``D`` plus ``other`` (HELIOS Eq. 2), grown by Eq. 3,
``gamma_n^c += sum_i y_i^c kappa(p_i, x~_n)``, with ``y_i`` the one-hot class of pixel ``i`` over ``D`` and
``other``. The next task in the house asks for other classes ``D'``, so the concentrations cannot be carried over
as they are: their ``other`` column means "none of ``D``", not "none of ``D'``".

**What is kept** (:class:`HomeObjects`): per Gaussian its geometry (mean, sigma, opacity: nothing is trained), a
home-wide id, and its Eq. 3 evidence *without the prior*, keyed by (vocabulary, label): the vocabulary ``V`` is the
set of classes the detector was asked for when the evidence was gathered, the label one class of ``V`` or
``other``. Each column is the sum of the kappa-weighted one-hot entries Eq. 3 added for that label while ``V``
was the vocabulary.

**The carry-over rule** (:meth:`HomeObjects.gamma_for`; a task starts with the Gaussians holding evidence for
one of its classes, :meth:`HomeObjects.restorable`): for a task with classes ``D`` a Gaussian starts with

* ``gamma^d = prior + sum over every V containing d of evidence[V, d]`` for ``d`` in ``D``: a pixel labelled
  ``d`` was ``d`` whatever else was asked;
* ``gamma^other = prior + sum over every V containing all of D of (evidence[V, other] + sum over e in V \\ D of
  evidence[V, e])``: a pixel labelled ``other`` under ``V`` was none of ``V``, hence none of ``D`` when ``D`` is
  inside ``V``; a pixel labelled ``e`` (not in ``D``) under such a ``V`` was ``e`` rather than any class of
  ``D`` the detector was also asked for (Eq. 3's ``y`` is one-hot: the best detection names the pixel);
* every other observation is left out: its one-hot ``y`` over ``D`` and ``other`` is unknown. In particular
  ``other`` from a task that did not ask for ``c`` is **not** evidence against ``c`` (the detector was never
  asked whether the pixel showed a ``c``), and neither is a pixel labelled ``e`` then.

Why leaving ambiguous evidence out is the safe side: the Gaussian keeps a flatter Dirichlet, so Eq. 4's variance
is larger and its expectation less extreme, Eq. 7's ``Psi = S - alpha_cs U`` is lower (no false certainty for or
against a target) and Eq. 5's entropy, hence Eq. 8-12's information gain, higher: the search is drawn to look
again rather than skip. Counting it as ``other`` would do the opposite and send the search past an object the
earlier tasks never asked the detector about.

At a task's end (:func:`commit_layer`) the episode's own evidence (its end concentrations minus those it
started with, per Gaussian) is added under its vocabulary ``D``; new Gaussians get a new home id. Two episodes
of one home at once: each started from a stored layer it keeps a copy of, so at its end its own evidence is
known exactly, and it is added to the layer stored by then (``onto``): Eq. 3's evidence is a sum of counts, so
both episodes' additions are kept whole, as if they had run one after the other. Explored floor is OR-ed per
class.

**Explored per class** (:class:`FloorMask`): the floor cells explored (the map's narrow field of view, Explore-EQA
appendix B) by an episode whose detector was asked for the class. A task counts as explored only the cells
explored for *every* one of its classes (:func:`explored_for`), so its search never skips floor where one of its
targets could stand and was never looked for.

Bounds (:meth:`HomeObjects.bounded`): at most ``max_gaussians`` (the Gaussians whose latest evidence is oldest
go first, ties: the least evidence), at most :data:`MAX_VOCABULARIES` vocabularies (the oldest go, with their
columns and the explored floor of classes no kept vocabulary asks for), and a byte budget (the commit halves the
count until the part fits).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from eqa.codec import packb, packed_array, unpackb
from services.mapper.home_memory import MAX_DECODED_HOME, union_grid

HOME_OBJECTS_VERSION = 1
OTHER = "other"
MAX_VOCABULARIES = 16  # distinct class sets a home keeps evidence for (tasks ask 1-3 classes each)
MAX_CLASS_CHARS = 80  # eqa.messages.ClassName

Vocabulary = tuple[str, ...]
Column = tuple[Vocabulary, str]  # (the classes asked, the label: one of them or "other")


def vocabulary(classes: Sequence[str]) -> Vocabulary:
    """A vocabulary's key: its class names, sorted (the order a task lists them in does not matter)."""
    names = sorted({str(c) for c in classes})
    if not names or any(not c or c == OTHER or len(c) > MAX_CLASS_CHARS for c in names):
        raise ValueError(f"a vocabulary is 1.. class names of 1..{MAX_CLASS_CHARS} characters, not {OTHER!r}")
    return tuple(names)


@dataclass
class FloorMask:
    """Floor cells on a grid of ``resolution`` m cells whose cell (0, 0) has its corner at (``x0``, ``y0``);
    ``mask`` is (rows along y, columns along x), as the map's 2D planes."""

    resolution: float
    x0: float
    y0: float
    mask: np.ndarray  # (ny, nx) bool

    def union(self, other: FloorMask) -> FloorMask:
        if abs(other.resolution - self.resolution) > 1e-9:
            raise ValueError("floor masks of different resolutions")
        x0, y0, shape, places = union_grid(self.resolution, [(self.x0, self.y0, self.mask.shape),
                                                             (other.x0, other.y0, other.mask.shape)])
        out = np.zeros(shape, dtype=bool)
        out[places[0]] |= self.mask
        out[places[1]] |= other.mask
        return FloorMask(self.resolution, x0, y0, out)

    def on_grid(self, x0: float, y0: float, shape: tuple[int, int]) -> np.ndarray:
        """The mask on another grid of the same resolution (cells outside this mask: False)."""
        out = np.zeros(shape, dtype=bool)
        r0 = round((self.y0 - y0) / self.resolution)
        c0 = round((self.x0 - x0) / self.resolution)
        ny, nx = self.mask.shape
        rs, cs = max(r0, 0), max(c0, 0)
        re, ce = min(r0 + ny, shape[0]), min(c0 + nx, shape[1])
        if rs < re and cs < ce:
            out[rs:re, cs:ce] = self.mask[rs - r0:re - r0, cs - c0:ce - c0]
        return out

    def cells(self) -> int:
        return int(self.mask.sum())

    def to_json(self) -> dict[str, Any]:
        return {"resolution": self.resolution, "origin": [self.x0, self.y0], "shape": list(self.mask.shape),
                "bits": packed_array(np.packbits(self.mask, axis=None))}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> FloorMask:
        shape = tuple(int(s) for s in d["shape"])
        if len(shape) != 2 or min(shape) < 0 or math.prod(shape) > MAX_DECODED_HOME:
            raise ValueError(f"bad floor mask shape {shape}")
        mask = np.unpackbits(np.asarray(d["bits"], dtype=np.uint8), count=math.prod(shape)).astype(bool)
        return cls(float(d["resolution"]), float(d["origin"][0]), float(d["origin"][1]), mask.reshape(shape))


def floor_of(volume: Any, resolution: float) -> FloorMask:
    """The explored floor of a TSDF volume (:class:`services.mapper.tsdf.TSDFVolume`, cells of ``resolution``
    m): cells with an explored voxel, on the volume's grid."""
    explored = volume.explored.any(axis=2) if volume.explored.size else np.zeros(volume.shape2d, dtype=bool)
    return FloorMask(float(resolution), float(volume.origin_x), float(volume.origin_y),
                     np.asarray(explored, dtype=bool).copy())


@dataclass
class HomeObjects:
    """A home's object layer (module doc). Rows are Gaussians; ``evidence`` has one column per ``columns``
    entry."""

    uid: np.ndarray  # (N,) int64 home-wide id
    means: np.ndarray  # (N, 3) float32 world
    sigma: np.ndarray  # (N,) float32 m
    opacity: np.ndarray  # (N,) float32
    seen: np.ndarray  # (N,) float64 unix time of the last episode that gave it evidence
    columns: list[Column]
    evidence: np.ndarray  # (N, K) float32, Eq. 3 sums without the prior, >= 0
    explored: dict[str, FloorMask] = field(default_factory=dict)
    vocabularies: list[Vocabulary] = field(default_factory=list)  # oldest first

    @classmethod
    def empty(cls) -> HomeObjects:
        return cls(np.zeros(0, np.int64), np.zeros((0, 3), np.float32), np.zeros(0, np.float32),
                   np.zeros(0, np.float32), np.zeros(0, np.float64), [], np.zeros((0, 0), np.float32))

    def __len__(self) -> int:
        return int(self.uid.shape[0])

    @property
    def classes(self) -> list[str]:
        """Every class some task of the home asked for."""
        return sorted({c for v in self.vocabularies for c in v})

    def asked(self, cls: str) -> bool:
        return any(cls in v for v in self.vocabularies)

    def gamma_for(self, classes: Sequence[str], prior: float) -> np.ndarray:
        """The concentrations (N, len(classes) + 1) a task with ``classes`` (then ``other``) starts with: the
        carry-over rule of the module doc (HELIOS Eq. 3-5)."""
        want = list(classes)
        d = set(want)
        out = np.full((len(self), len(want) + 1), float(prior), dtype=np.float32)
        for k, (voc, label) in enumerate(self.columns):
            col = self.evidence[:, k]
            if label in d:
                out[:, want.index(label)] += col
            elif d <= set(voc):  # labelled other, or a class of V outside D: none of D
                out[:, -1] += col
        return out

    def restorable(self, classes: Sequence[str], prior: float,
                   rule: str = "evidence") -> tuple[np.ndarray, np.ndarray]:
        """The Gaussians a task with ``classes`` starts with and their concentrations (:meth:`gamma_for`).
        ``rule`` "evidence" (``EQA_HOME_RESTORE_OBJECTS``): those holding evidence for at least one of its
        classes. HELIOS creates a Gaussian only inside pixels detected as a task class (appendix 6.1, "Gaussian
        creation"), so a task's own layer never holds one without such evidence; restored with the flat prior over
        (class, other), such a Gaussian has ``S_c = 1/2`` for a one-class task (Eq. 4), above the candidate bar
        ``cs`` of Eq. 7, and the search may go to look at remembered objects of other classes. "all": every
        Gaussian, those at the flat prior included (they are still places to look at). Returns (indices into this
        layer, concentrations)."""
        if rule not in ("evidence", "all"):
            raise ValueError(f"restore rule {rule!r}: expected 'evidence' or 'all'")
        gamma = self.gamma_for(classes, prior)
        if rule == "all":
            return np.arange(len(self)), gamma
        keep = np.nonzero((gamma[:, :-1] - float(prior)).sum(axis=1) > 0)[0]
        return keep, gamma[keep]

    def explored_for(self, classes: Sequence[str]) -> FloorMask | None:
        """The floor explored for every one of ``classes`` (None: some class was never looked for)."""
        masks = [self.explored.get(c) for c in classes]
        if not masks or any(m is None for m in masks):
            return None
        first = masks[0]
        assert first is not None
        out = first.mask.copy()
        for m in masks[1:]:
            assert m is not None
            out &= m.on_grid(first.x0, first.y0, first.mask.shape)
        return FloorMask(first.resolution, first.x0, first.y0, out)

    # ---- combining ---------------------------------------------------------------------------------------
    def _aligned(self, columns: list[Column]) -> np.ndarray:
        """This layer's evidence on ``columns`` (a superset of its own), zeros elsewhere."""
        out = np.zeros((len(self), len(columns)), dtype=np.float32)
        where = {c: i for i, c in enumerate(columns)}
        for k, c in enumerate(self.columns):
            out[:, where[c]] = self.evidence[:, k]
        return out

    def select(self, keep: np.ndarray) -> HomeObjects:
        return replace(self, uid=self.uid[keep], means=self.means[keep], sigma=self.sigma[keep],
                       opacity=self.opacity[keep], seen=self.seen[keep], evidence=self.evidence[keep])

    def bounded(self, max_gaussians: int, max_vocabularies: int = MAX_VOCABULARIES) -> HomeObjects:
        """The layer within the bounds of the module doc."""
        out = self
        if len(out.vocabularies) > max_vocabularies:
            kept = out.vocabularies[-max_vocabularies:] if max_vocabularies > 0 else []
            cols = [k for k, (v, _) in enumerate(out.columns) if v in kept]
            names = {c for v in kept for c in v}
            out = replace(out, vocabularies=list(kept), columns=[out.columns[k] for k in cols],
                          evidence=out.evidence[:, cols],
                          explored={n: m for n, m in out.explored.items() if n in names})
        if len(out) > max_gaussians:
            total = out.evidence.sum(axis=1).astype(np.float64)
            order = np.lexsort((-total, -out.seen))  # newest evidence first, then most evidence
            out = out.select(np.sort(order[:max(max_gaussians, 0)]))
        return out

    # ---- bytes -------------------------------------------------------------------------------------------
    def to_bytes(self) -> bytes:
        return packb({
            "version": HOME_OBJECTS_VERSION, "uid": packed_array(np.ascontiguousarray(self.uid, np.int64)),
            "means": packed_array(np.ascontiguousarray(self.means, np.float32)),
            "sigma": packed_array(np.ascontiguousarray(self.sigma, np.float32)),
            "opacity": packed_array(np.ascontiguousarray(self.opacity, np.float32)),
            "seen": packed_array(np.ascontiguousarray(self.seen, np.float64)),
            "columns": [[list(v), label] for v, label in self.columns],
            "evidence": packed_array(np.ascontiguousarray(self.evidence, np.float32)),
            "vocabularies": [list(v) for v in self.vocabularies],
            "explored": {name: m.to_json() for name, m in self.explored.items()},
        })

    @classmethod
    def from_bytes(cls, data: bytes) -> HomeObjects:
        b = unpackb(data, max_decoded=MAX_DECODED_HOME)
        if not isinstance(b, dict) or b.get("version") != HOME_OBJECTS_VERSION:
            raise ValueError(f"not a home object layer of version {HOME_OBJECTS_VERSION}")
        vocabularies = [vocabulary(v) for v in b["vocabularies"]]
        columns: list[Column] = []
        for v, label in b["columns"]:
            voc = vocabulary(v)
            if voc not in vocabularies or (label != OTHER and label not in voc):
                raise ValueError(f"column {voc}/{label} of no vocabulary")
            columns.append((voc, str(label)))
        uid = np.asarray(b["uid"], dtype=np.int64).reshape(-1)
        n = len(uid)
        means = np.asarray(b["means"], dtype=np.float32).reshape(n, 3)
        evidence = np.asarray(b["evidence"], dtype=np.float32).reshape(n, len(columns))
        sigma = np.asarray(b["sigma"], dtype=np.float32).reshape(n)
        opacity = np.asarray(b["opacity"], dtype=np.float32).reshape(n)
        if not (np.isfinite(means).all() and np.isfinite(evidence).all() and (evidence >= 0).all()
                and (sigma > 0).all() and ((opacity > 0) & (opacity < 1)).all()):
            raise ValueError("home object layer with non-finite or out-of-range values")
        if len(np.unique(uid)) != n:
            raise ValueError("home object layer with repeated ids")
        explored = {str(k): FloorMask.from_json(m) for k, m in dict(b["explored"]).items()}
        return cls(uid, means, sigma, opacity, np.asarray(b["seen"], dtype=np.float64).reshape(n), columns,
                   evidence, explored, vocabularies)


def new_uids(episode_id: str, start: int, n: int) -> np.ndarray:
    """Home ids of an episode's new Gaussians: the episode's CRC in the high 31 bits, a counter below, so two
    episodes of one home committing at once do not collide (unless two episode ids share a CRC-32 and a counter
    range)."""
    base = np.int64(zlib.crc32(episode_id.encode()) & 0x7FFFFFFF) << np.int64(32)
    return base + np.arange(start, start + n, dtype=np.int64)


def commit_layer(base: HomeObjects | None, uid: np.ndarray, means: np.ndarray, sigma: np.ndarray,
                 opacity: np.ndarray, gamma: np.ndarray, classes: Sequence[str], prior: float, episode_id: str,
                 now: float, explored: FloorMask | None, onto: HomeObjects | None = None) -> HomeObjects:
    """The home layer after a task episode: the episode's own evidence added under its vocabulary (module doc)
    to ``onto`` (the layer stored now; None: ``base``). ``base`` is the layer the episode started from (None:
    none); the episode's end layer has ``uid`` -1 for Gaussians it made and ``gamma`` (N, len(classes) + 1), the
    last column ``other``. Its own evidence per Gaussian is the concentrations it ended with minus those it
    started with (:meth:`HomeObjects.gamma_for` of ``base``, the prior for a new one): Eq. 3's counts add, so two
    episodes of one home committed one after the other, each onto what the other stored, keep both episodes'
    evidence whole, whatever order they end in. A Gaussian of ``base`` that ``onto`` no longer holds (dropped by
    the bounds meanwhile) comes back with this episode's evidence only. ``explored``: the episode's explored
    floor, counted for each of ``classes``."""
    base = base if base is not None else HomeObjects.empty()
    onto = onto if onto is not None else base
    voc = vocabulary(classes)
    names = list(classes)
    mine: list[Column] = [(voc, c) for c in names] + [(voc, OTHER)]
    columns = list(dict.fromkeys([*onto.columns, *mine]))
    evidence = onto._aligned(columns)
    start = base.gamma_for(names, prior)
    started = {int(u): i for i, u in enumerate(base.uid)}
    from_base = np.array([started.get(int(u), -1) for u in uid], dtype=np.int64)
    begin = np.full(gamma.shape, float(prior), dtype=np.float32)
    begin[from_base >= 0] = start[from_base[from_base >= 0]]
    delta = np.clip(np.asarray(gamma, dtype=np.float32) - begin, 0.0, None)
    order = {int(u): i for i, u in enumerate(onto.uid)}
    rows = np.array([order.get(int(u), -1) for u in uid], dtype=np.int64)
    known = rows >= 0
    cols = [columns.index(c) for c in mine]
    evidence[np.ix_(rows[known], cols)] += delta[known]
    seen = onto.seen.copy()
    touched = known & (delta.sum(axis=1) > 0)
    seen[rows[touched]] = now
    fresh = ~known
    n_new = int(fresh.sum())
    new_ev = np.zeros((n_new, len(columns)), dtype=np.float32)
    new_ev[:, cols] = delta[fresh]
    ids = np.asarray(uid, dtype=np.int64)[fresh]
    made = ids < 0
    ids[made] = new_uids(episode_id, 0, int(made.sum()))
    explored_masks = dict(onto.explored)
    if explored is not None:
        for c in names:
            explored_masks[c] = explored_masks[c].union(explored) if c in explored_masks else explored
    vocabularies = [v for v in onto.vocabularies if v != voc] + [voc]  # the newest last (bounded() drops oldest)
    return HomeObjects(
        np.concatenate([onto.uid, ids]),
        np.concatenate([onto.means, np.asarray(means, np.float32)[fresh].reshape(-1, 3)]),
        np.concatenate([onto.sigma, np.asarray(sigma, np.float32)[fresh]]),
        np.concatenate([onto.opacity, np.asarray(opacity, np.float32)[fresh]]),
        np.concatenate([seen, np.full(n_new, now, dtype=np.float64)]), columns,
        np.concatenate([evidence, new_ev]), explored_masks, vocabularies)
