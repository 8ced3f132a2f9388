"""Initial body fit to a full scan (paper §4.1): shape, pose and placement of Anny.

Two kinds of stages, both robust and *clothing-aware*:

- Coarse (Adam, correspondences re-computed every step): placement (yaw and translation), then pose,
  from two starts: sized by the scan's height and standing on its lowest point, and of average height
  hung from the top of the head (for scans that miss the feet); the lower loss goes on.
  Each scan point is matched to its nearest body vertex (point-to-plane along the vertex normal, plus a
  little of the tangential part) and each body vertex to the mean of its nearest scan points, under a
  Geman–McClure kernel. A scan point whose *denoised* offset (the mean offset of its ``offset_knn`` scan
  neighbours) lies more than ``clothing_margin`` outside the body weighs only ``cloth_weight``.
  The pelvis is kept upright (yaw only): a tilted pelvis mimics sideways legs and traps the pose.
- Final (L-BFGS, ICP rounds): each round matches every scan point to the exact closest point of the body
  surface (`geometry.closest_point_on_mesh`) and labels it clothing when its denoised offset exceeds
  ``clothing_margin``, except on the extremities (head, hands, feet: no garment of ours covers them);
  labels are sticky (once clothing, always clothing). Then L-BFGS minimizes, with the
  matches held fixed, a Geman–McClure penalty of the denoised point-to-surface offset: symmetric on skin
  (unbiased under noise: the offset of a noisy sample of the true surface averages to zero), one-sided on
  clothing (the body may lie anywhere inside the cloth, never outside it). All parameters — placement,
  pose and the phenotypes — move together.

Why (measured on synthetic Anny scans, 1 cm noise, 20 % holes; see ``scripts/body_fit_seeds.py``):
point-to-vertex residuals and k-NN-mean targets are biased on 1 cm noise (thin fingers and toes, curved
parts, hole rims), and any asymmetry applied to *raw* noisy offsets shrinks the body; both biases turn
into centimetres of height because height is a weak direction of the phenotype space. Adam alone stopped
short of the optimum of that ill-conditioned valley; L-BFGS on fixed matches reaches it. A shape stage
before the final one made the body swell under clothing, and non-sticky labels let the body creep into
the thinnest cloth. Without the extremities held as skin, a body that started too thin for a bare scan
took most of it for clothing and came out short (measured over seeds 0-9: 5 of 10 beyond 1 cm in height
or 1.5 cm per vertex before, all within after; see ``scripts/body_fit_seeds.py``).

Priors: soft joint limits, a pull toward the A-pose, a weak pull of the phenotypes toward 0.5, and a
self-penetration proxy (forearms/hands vs torso/hips/thighs, shin vs shin; see
`priors.self_penetration_penalty`).
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree

from torch_diffavatar.body.facing import facing_yaws, shows_feet
from torch_diffavatar.body.geometry import face_normals, vertex_areas, vertex_normals
from torch_diffavatar.body.model import BodyModel
from torch_diffavatar.body.parts import PART_NAMES
from torch_diffavatar.body.priors import joint_limit_penalty, pose_prior, self_penetration_penalty
from torch_diffavatar.chamfer import nearest_indices
from torch_diffavatar.errors import ScanError
from torch_diffavatar.forked import side_by_side
from torch_diffavatar.geometry import closest_point_on_mesh

SOLE_DEPTH = 0.01  # [m] a foot's vertices this close to its lowest in the rest pose: the sole, heel to toe


@dataclass
class BodyFitConfig:
    """Knobs of `fit_body` (defaults are what the tests and the CLI use).

    Attributes:
        max_scan_points: scan points used by the loss (a fixed random subset) [count].
        yaw_candidates: initial rotations about the up axis [deg]; the coarse stages run from each (the
            soles start) and the fit goes on from the one whose result the final stage's energy scores
            lowest (`_coarse`); a start within ``facing_tolerance_deg`` of an earlier one is dropped
            (`_yaw_starts`). A brief placement alone (rotation and translation, 12 steps) chose the
            back on 4 of 10 randomly posed scans: the back of a body placed on the front fits it well
            before the limbs move (docs/BENCHMARKS.md, "Front or back").
        yaw_from_scan: turn the ``yaw_candidates`` by the scan's own facing direction
            (`body.facing.facing_yaws`: hips axis and feet) when it lies farther than
            ``facing_tolerance_deg`` [deg] from 0, for a person facing any way (a capture turned 59° ended
            at 3.3 cm Chamfer from the 0° start, issue #29). A direction within the tolerance is taken as
            0 (the estimate is ~2° on +Z scans, and the placement stage corrects that itself). The scan
            gives two opposite directions (front or back unknown) and both are tried: before, one near 0
            made the other be dropped, and trousers captures facing 165-199° were fitted backwards; and
            the feet's side alone, taken as the front, turned a long dress captured from its side
            backwards.
        upright_coarse: keep the pelvis upright (yaw only) in the coarse stages.
        placement_iters, pose_iters: Adam steps of the coarse stages.
        final_rounds, final_iters: the final stage: ``final_rounds`` rounds of exact point-to-surface
            matches, each followed by up to ``final_iters`` L-BFGS iterations with them held fixed.
        lr_rotation [rad], lr_translation [m], lr_pose [rad]: Adam step sizes of the coarse stages.
        robust_scale, final_robust_scale: Geman–McClure scale [m] in the coarse stages and the final one.
        cloth_weight: coarse-stage data weight of scan points that look like clothing.
        clothing_margin: denoised outward offset [m] beyond which a scan point looks like clothing
            (coarse stages: a logistic step of width ``margin_width`` [m]; final stage: a hard label).
            About 3.4 standard deviations of the denoised offset for 1 cm scan noise.
        offset_knn: scan neighbours averaged into a scan point's denoised offset.
        target_knn: scan points averaged into each body vertex's target (coarse body→scan term).
        body_to_scan_weight: weight of the coarse body→scan term.
        tangent_weight: weight of the tangential part of a coarse residual (the normal part weighs 1).
        max_distance: scan points farther than this from the body [m] get no final-stage match (the
            robust kernel is saturated there).
        pose_prior_weight, joint_limit_weight, phenotype_prior_weight, penetration_weight: prior weights.
            The pose prior decides the pose of a part the scan's holes hide (measured: with 1e-3 a hand
            mostly cut away came out 6 cm off, 0.9 cm with 1e-2).
        penetration_margin: distance [m] below which non-adjacent parts are pushed apart.
        skin_parts: body parts (`PART_NAMES`) that no garment of ours covers: final-stage scan points
            matched to them are never labelled clothing (so they fix the body's size and its height).
            Limitation: shoes, gloves, hats or long hair break this assumption.
        head_start: besides the start sized by the scan's height with the soles on its lowest point, run
            the coarse stages from a body of average height hung from the top of the head too, and go on
            from the one whose pose-stage loss is lower (the coarse stages run once more). A
            scan cut above the feet (a capture that misses them) makes the first start far too short.
            Measured on simulated dress scans cut 30 cm above their lowest point, seeds 0-2
            (``scripts/body_fit_seeds.py --missing-bottom 0.3``): height error -3.3 / -8.9 / -4.6 cm
            before it (4902e0d), -0.1 / +1.2 / -0.7 cm with it; complete scans keep the first start.
            Body vertices below every scan point are left out of the coarse body→scan term either way
            (not observed). A scan that shows its feet (`body.facing.shows_feet`) keeps the first start
            alone: the head start won on 1 of 15 complete scans only (a worse body there), and skipping
            it saves about a third of the body fit's time (issue #32).
        floor_weight: weight of the floor term, when `fit_body` is given the floor's height: the soles
            (`SOLE_DEPTH`), heel to toe, held on it as they lie in the rest pose, mean of (Δ / 1 cm)² [-].
            Trousers or a long hem that reach the floor hide the feet, and a body under clothing is held
            only inside it: on capture-simulated trousers whose hems cover the feet, the fitted soles
            ended 2.5-3 cm above the floor and the bodies 2.1-3.0 cm short; held by their lowest vertices
            only, the feet stood on tiptoe (docs/BENCHMARKS.md, "The body fit on captures: the floor
            under trousers").
        seed: seed of the scan subsampling.
    """

    max_scan_points: int = 20000
    yaw_candidates: tuple[float, ...] = (0.0,)
    yaw_from_scan: bool = True
    facing_tolerance_deg: float = 20.0
    upright_coarse: bool = True
    placement_iters: int = 25
    pose_iters: int = 60
    final_rounds: int = 10
    final_iters: int = 15
    lr_rotation: float = 0.02
    lr_translation: float = 0.01
    lr_pose: float = 0.03
    robust_scale: float = 0.04
    final_robust_scale: float = 0.02
    cloth_weight: float = 0.3
    clothing_margin: float = 0.006
    margin_width: float = 0.002
    offset_knn: int = 32
    target_knn: int = 8
    body_to_scan_weight: float = 1.0
    tangent_weight: float = 0.1
    max_distance: float = 0.1
    pose_prior_weight: float = 1e-2
    joint_limit_weight: float = 10.0
    phenotype_prior_weight: float = 1e-3
    penetration_weight: float = 1e4
    penetration_margin: float = 0.01
    skin_parts: tuple[str, ...] = ("head", "hand.L", "hand.R", "foot.L", "foot.R")
    head_start: bool = True
    floor_weight: float = 0.01
    seed: int = 0


@dataclass
class BodyFitResult:
    """What `fit_body` returns.

    Attributes:
        body: the fitted `BodyModel` (batch 1).
        chamfer_m: symmetric mean distance [m] between all scan points and the fitted body's vertices,
            ``(mean_scan→body + mean_body→scan) / 2`` (nearest vertex / nearest scan point).
        height_m: standing height [m] of the fitted body (A-pose, times scale).
        seconds: wall time of the fit [s].
        yaw_deg: the initial yaw candidate that won [deg].
        start: the starting body that won (``"soles"`` or ``"head"``, see `BodyFitConfig.head_start`).
        losses: final loss of each stage (``pose_soles``, ``pose_head``: of the pose stage from each start
            that ran; no ``pose_head`` when the scan shows its feet).
    """

    body: BodyModel
    chamfer_m: float
    height_m: float
    seconds: float
    yaw_deg: float
    start: str = "soles"
    losses: dict[str, float] = field(default_factory=dict)


def _check_scan(points: torch.Tensor) -> None:
    if points.dim() != 2 or points.shape[1] != 3:
        raise ScanError(f"scan points must have shape (N, 3), got {tuple(points.shape)}")
    if points.shape[0] < 100:
        raise ScanError(f"scan has only {points.shape[0]} points; a body fit needs at least 100")
    if not torch.isfinite(points).all():
        raise ScanError("scan points contain NaN or infinite coordinates")


def _gm(sq: torch.Tensor, scale: float) -> torch.Tensor:
    """Normalized Geman–McClure: d²/(d² + s²), in [0, 1)."""
    return sq / (sq + scale * scale)


@dataclass
class _Matches:
    """Matches held fixed while the body moves (no gradient flows through them).

    Scan point n matches the body point ``Σ_k scan_bary[n, k] · verts[scan_verts[n, k]]`` with normal
    ``scan_normal[n]``; coarse stages also match body vertex v to the point ``vert_target[v]``.
    """

    scan_verts: torch.Tensor  # (N, 3) int64
    scan_bary: torch.Tensor  # (N, 3)
    scan_normal: torch.Tensor  # (N, 3) unit
    scan_found: torch.Tensor  # (N,) bool, False beyond max_distance (saturated penalty, no gradient)
    scan_cloth: torch.Tensor  # (N,) bool, denoised offset beyond the clothing margin
    scan_weight: torch.Tensor | None = None  # (N,) coarse data weight
    vert_target: torch.Tensor | None = None  # (V, 3)
    vert_normal: torch.Tensor | None = None  # (V, 3) unit
    vert_weight: torch.Tensor | None = None  # (V,) area × clothing weight


class _Objective:
    """Loss of one body against one scan, split into matching (`match`) and energy (`energy`).

    ``final`` switches from the coarse loss (nearest-vertex matches, cloth-weighted two-sided robust
    Chamfer) to the final one (exact surface matches, denoised offsets, clothing labels); see the module
    docstring.
    """

    def __init__(self, body: BodyModel, scan: torch.Tensor, cfg: BodyFitConfig, floor_y: float | None = None):
        self.body, self.cfg, self.floor_y = body, cfg, floor_y
        self.final = False
        with torch.no_grad():
            rest = body()
            self.vert_area = vertex_areas(rest.vertices[0], rest.faces)  # (V,) [m²]
        # the scan in the body's precision (a float32 scan file with a float64 body model, or vice versa)
        self.scan = scan = scan.to(rest.vertices.dtype)
        self.pairs = self._penetration_pairs()
        unknown = [n for n in cfg.skin_parts if n not in PART_NAMES]
        if unknown:
            raise ValueError(f"unknown skin_parts {unknown}; known body parts: {PART_NAMES}")
        skin_ids = body.vertex_parts.new_tensor([PART_NAMES.index(n) for n in cfg.skin_parts])
        self.vert_skin = torch.isin(body.vertex_parts, skin_ids)  # (V,) bool: never under clothing
        # the soles the floor term holds: an Anny forward pass, only when there is a floor
        self.sole_ids, self.sole_lift = _sole_vertices(body) if floor_y is not None else (None, None)
        self.scan_tree = cKDTree(scan.numpy())
        k = min(cfg.offset_knn, scan.shape[0])
        _, nbr = self.scan_tree.query(scan.numpy(), k=k)
        self.scan_nbr = torch.from_numpy(nbr.reshape(scan.shape[0], k))  # (N, k), the point itself included
        # Below this height nothing was observed (a scan cut above the feet): no body→scan pull there.
        self.unobserved_below = _scan_extent(scan)[0] - 0.02

    def _penetration_pairs(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        b = self.body

        def sub(names, step):
            return b.part_indices(*names)[::step]

        trunk = sub(("torso", "hips", "thigh.L", "thigh.R"), 4)
        return [
            (sub(("forearm.L", "hand.L"), 8), trunk),
            (sub(("forearm.R", "hand.R"), 8), trunk),
            (sub(("shin.L",), 2), sub(("shin.R",), 2)),
        ]

    def _cloth_weight(self, offset: torch.Tensor) -> torch.Tensor:
        """Data weight from a denoised outward offset [m]: 1 on skin, ``cloth_weight`` on clothing."""
        cfg = self.cfg
        step = torch.sigmoid((offset - cfg.clothing_margin) / cfg.margin_width)
        return 1.0 + (cfg.cloth_weight - 1.0) * step

    @torch.no_grad()
    def match(self, verts: torch.Tensor, faces: torch.Tensor) -> _Matches:
        """Matches and data weights for body vertices ``verts`` (V, 3) [m], faces (F, 3)."""
        cfg, scan = self.cfg, self.scan
        n_scan = scan.shape[0]
        if self.final:
            tri, bary, _ = closest_point_on_mesh(scan, verts, faces, cfg.max_distance)
            found = tri >= 0
            tri = tri.clamp_min(0)
            fn = face_normals(verts, faces)[tri]
            scan_normal = fn / fn.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            scan_verts = faces[tri]
        else:
            nearest = torch.from_numpy(nearest_indices(scan, verts))
            scan_verts = nearest[:, None].expand(n_scan, 3)
            bary = torch.zeros(n_scan, 3, dtype=scan.dtype)
            bary[:, 0] = 1.0
            found = torch.ones(n_scan, dtype=torch.bool)
            vert_normal = vertex_normals(verts, faces)  # (V, 3), the body→scan term's too
            scan_normal = vert_normal[nearest]
        q = (bary[:, :, None] * verts[scan_verts]).sum(1)
        offset = ((scan - q) * scan_normal).sum(-1)  # (N,) positive outside the body
        offset_bar = offset[self.scan_nbr].mean(1)  # (N,) denoised
        m = _Matches(scan_verts, bary, scan_normal, found, offset_bar > cfg.clothing_margin)
        if self.final:
            # Scan points on the extremities are skin whatever their offset: else a body that starts
            # too thin for a bare scan labels most of it clothing (sticky), shrinks into it and comes
            # out short (measured: 4 of 10 seeds 1.1-1.6 cm short, 62 % of a bare scan "clothing").
            m.scan_cloth &= ~self.vert_skin[scan_verts[:, 0]]
            return m
        m.scan_weight = self._cloth_weight(offset_bar)
        m.vert_normal = vert_normal
        _, idx = self.scan_tree.query(verts.numpy(), k=cfg.target_knn)
        m.vert_target = scan[torch.from_numpy(idx.reshape(len(verts), -1))].mean(1)  # (V, 3)
        m.vert_weight = self.vert_area * self._cloth_weight(((m.vert_target - verts) * m.vert_normal).sum(-1))
        m.vert_weight = m.vert_weight * (verts[:, 1] >= self.unobserved_below)
        return m

    def data_terms(self, verts: torch.Tensor, m: _Matches) -> torch.Tensor:
        """Robust data term of body vertices ``verts`` (V, 3) [m] under matches ``m``, a mean in [0, 2)."""
        cfg = self.cfg
        q = (m.scan_bary[:, :, None] * verts[m.scan_verts]).sum(1)  # (N, 3), differentiable
        diff = self.scan - q
        s = (diff * m.scan_normal).sum(-1)  # (N,) positive outside the body
        if self.final:
            s = torch.where(m.scan_found, s, cfg.max_distance)
            s_bar = s[self.scan_nbr].mean(1)  # (N,) denoised offset
            s_bar = torch.where(m.scan_cloth, s_bar.clamp_max(0.0), s_bar)  # clothing: one-sided
            return _gm(s_bar**2, cfg.final_robust_scale).mean()
        scale = cfg.robust_scale
        tangent_sq = ((diff**2).sum(-1) - s**2).clamp_min(0.0)
        e_sb = (m.scan_weight * _gm(s**2 + cfg.tangent_weight * tangent_sq, scale)).mean()
        diff = m.vert_target - verts
        s = (diff * m.vert_normal).sum(-1)
        tangent_sq = ((diff**2).sum(-1) - s**2).clamp_min(0.0)
        pen = _gm(s**2 + cfg.tangent_weight * tangent_sq, scale)
        e_bs = (m.vert_weight * pen).sum() / m.vert_weight.sum().clamp_min(1e-12)
        return e_sb + cfg.body_to_scan_weight * e_bs

    def energy(self, out, m: _Matches) -> torch.Tensor:
        """Data term plus priors of a body output ``out`` (a `BodyOutput`) under matches ``m``."""
        b, cfg = self.body, self.cfg
        loss = self.data_terms(out.vertices[0], m)
        loss = loss + cfg.pose_prior_weight * pose_prior(b.pose).sum()
        loss = loss + cfg.joint_limit_weight * joint_limit_penalty(b.pose, b.pose_lower, b.pose_upper).sum()
        loss = loss + cfg.phenotype_prior_weight * ((b.phenotypes - 0.5) ** 2).sum()
        loss = (
            loss
            + cfg.penetration_weight
            * self_penetration_penalty(out.vertices, self.pairs, cfg.penetration_margin).sum()
        )
        if self.floor_y is not None:  # a standing person's soles are on the floor, seen or not
            soles = out.vertices[0, self.sole_ids, 1] - self.sole_lift.to(out.vertices)
            loss = loss + cfg.floor_weight * (((soles - self.floor_y) / 0.01) ** 2).mean()
        return loss

    def __call__(self) -> torch.Tensor:
        """The loss with correspondences re-computed at the current body."""
        out = self.body()
        return self.energy(out, self.match(out.vertices[0].detach(), out.faces))


@torch.no_grad()
def _sole_vertices(body: BodyModel) -> tuple[torch.Tensor, torch.Tensor]:
    """(k,) ids of the vertices of each foot within `SOLE_DEPTH` of that foot's lowest, in the rest pose
    at the default shape (the soles, heel to toe), and (k,) their heights above it there [m]."""
    state = {k: v.clone() for k, v in body.state_dict().items()}
    body.set_phenotypes(torch.full_like(body.phenotypes, 0.5))
    body.pose.zero_()
    body.global_orient.zero_()
    verts = body().vertices[0]
    body.load_state_dict(state)
    ids, lift = [], []
    for name in ("foot.L", "foot.R"):
        foot = body.part_indices(name)
        y = verts[foot, 1] - verts[foot, 1].min()
        ids.append(foot[y <= SOLE_DEPTH])
        lift.append(y[y <= SOLE_DEPTH])
    return torch.cat(ids), torch.cat(lift)


def _set_trainable(body: BodyModel, params: list[torch.Tensor]) -> None:
    for p in body.parameters():
        p.requires_grad_(False)
    for p in params:
        p.requires_grad_(True)


def _run_stage(objective: _Objective, groups: list[dict], iters: int) -> float:
    """Adam on ``groups`` with correspondences re-computed every step; returns the last loss."""
    params = [p for g in groups for p in g["params"]]
    body = objective.body
    _set_trainable(body, params)
    hook = None
    if objective.cfg.upright_coarse and body.global_orient.requires_grad:
        # Yaw only: a tilted pelvis would mimic sideways legs and trap the pose in a false minimum.
        yaw_only = body.global_orient.new_tensor([0.0, 1.0, 0.0])
        hook = body.global_orient.register_hook(lambda g: g * yaw_only)
    opt = torch.optim.Adam(groups)
    # Cosine decay to 5 % of the step size: Adam's steps do not shrink by themselves near the optimum.
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda i: 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * i / max(iters, 1)))
    )
    loss = torch.tensor(float("nan"))
    for _ in range(iters):
        opt.zero_grad(set_to_none=True)
        loss = objective()
        loss.backward()
        opt.step()
        sched.step()
    if hook is not None:
        hook.remove()
    _set_trainable(body, [])
    return float(loss.detach())


def _run_icp(objective: _Objective, params: list[torch.Tensor], rounds: int, iters: int) -> float:
    """``rounds`` × (correspondences at the current body, then ``iters`` L-BFGS steps with them fixed).

    With the correspondences fixed the loss is a smooth function of the body parameters, which L-BFGS
    (a quasi-Newton method, close to the paper's Gauss–Newton) minimizes far better than Adam.
    """
    body = objective.body
    _set_trainable(body, params)
    # One optimizer for all rounds: its curvature history stays useful as the matches change little.
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=iters, history_size=30, line_search_fn="strong_wolfe")
    matches = None

    def closure():
        opt.zero_grad(set_to_none=True)
        value = objective.energy(body(), matches)
        value.backward()
        return value

    cloth = None
    for _ in range(rounds):
        with torch.no_grad():
            out = body()
        matches = objective.match(out.vertices[0], out.faces)
        if cloth is not None:
            # Once clothing, always clothing: otherwise the body creeps into the thinnest cloth.
            matches.scan_cloth |= cloth
        cloth = matches.scan_cloth
        opt.step(closure)
    _set_trainable(body, [])
    if matches is None:
        return float("nan")
    with torch.no_grad():
        return float(objective.energy(body(), matches))


def _scan_extent(scan: torch.Tensor) -> tuple[float, float]:
    """(lowest, highest) height [m] of the scan, robust to a few outliers (0.1 % quantiles)."""
    q = torch.quantile(scan[:, 1], torch.tensor([0.001, 0.999], dtype=scan.dtype))
    return float(q[0]), float(q[1])


def _yaw_starts(scan: torch.Tensor, cfg: BodyFitConfig) -> list[float]:
    """The yaws [deg] the placement stage starts from: ``cfg.yaw_candidates``, turned by each of the scan's
    facing directions (`facing_yaws`: two opposite ones, the feet's side first) when ``cfg.yaw_from_scan``;
    a direction within ``cfg.facing_tolerance_deg`` of +Z turns them by 0, and a start within that of an
    earlier one is dropped."""
    facing = facing_yaws(scan.numpy()) if cfg.yaw_from_scan else []
    if not facing:
        return list(cfg.yaw_candidates)
    tol = cfg.facing_tolerance_deg
    facing = [0.0 if abs(f) <= tol else f for f in facing]  # +Z needs no turn
    starts = []
    for yaw in (f + y for f in facing for y in cfg.yaw_candidates):
        # one start for each way round: candidates 0 and 180 turned by both facing directions meet twice
        if all(abs((yaw - s + 180.0) % 360.0 - 180.0) > tol for s in starts):
            starts.append(yaw)
    return starts


@torch.no_grad()
def _initial_guess(body: BodyModel, scan: torch.Tensor, yaw_deg: float, start: str = "soles") -> None:
    """Shape, yaw and a bounding-box translation of a starting body.

    ``start="soles"``: the height phenotype from the scan's height (bisection), the soles on the scan's
    lowest point. ``"head"``: average phenotypes, the top of the head on the scan's highest point (for
    a scan that misses the feet).
    """
    lo_q, hi_q = _scan_extent(scan)
    body.set_phenotypes(torch.full_like(body.phenotypes, 0.5))
    if start == "soles":
        target = hi_q - lo_q
        lo, hi = 0.02, 0.98
        for _ in range(10):
            mid = 0.5 * (lo + hi)
            body.set_phenotypes({"height": mid})
            if float(body.standing_height()[0]) < target:
                lo = mid
            else:
                hi = mid
        body.set_phenotypes({"height": 0.5 * (lo + hi)})
    elif start != "head":
        raise ValueError(f"start must be 'soles' or 'head', got {start!r}")
    body.pose.zero_()
    body.translation.zero_()
    body.global_orient.copy_(torch.tensor([[0.0, math.radians(yaw_deg), 0.0]], dtype=scan.dtype))
    verts = body().vertices[0]
    shift = scan.median(0).values - verts.median(0).values
    if start == "soles":
        shift[1] = lo_q - float(verts[:, 1].min())
    else:
        shift[1] = hi_q - float(verts[:, 1].max())
    body.translation.copy_(shift[None])


def _coarse(objective: _Objective, yaw: float, start: str, placement: list[dict], pose: list[dict]) -> tuple:
    """The coarse stages (placement, then placement and pose) from the starting body of ``yaw`` [deg] and
    ``start`` (`_initial_guess`): ``(score, losses, yaw, start, state)``, the final stage's energy at their
    end (its exact surface matches and clothing labels, before any of its steps), the stages' last losses
    and the body's state dict.

    The score, not the pose stage's loss, tells front from back: on a randomly posed T-shirt scan the pose
    stage ended lower facing backwards (0.235 against 0.240), the final energy 0.127 against 0.084."""
    body = objective.body
    _initial_guess(body, objective.scan, yaw, start)
    losses = {"placement": _run_stage(objective, placement, objective.cfg.placement_iters)}
    losses["pose"] = _run_stage(objective, placement + pose, objective.cfg.pose_iters)
    objective.final = True
    with torch.no_grad():
        out = body()
        score = float(objective.energy(out, objective.match(out.vertices[0], out.faces)))
    objective.final = False
    return score, losses, yaw, start, {k: v.detach().clone() for k, v in body.state_dict().items()}


def _coarse_starts(objective: _Objective, yaws: list[float], placement, pose, workers: int) -> list[tuple]:
    """`_coarse` from the soles at each of ``yaws`` [deg], in order, up to ``workers`` at a time: the driver
    fits one while forked copies of it fit the next (`forked.side_by_side`), with the same results as one
    after another, since a start sets everything its stages train (`_initial_guess`). A start whose worker
    is lost (killed, out of memory) is fitted by the driver."""
    coarse = functools.partial(_coarse_from, objective, placement=placement, pose=pose)
    return [tuple(r) for r in side_by_side(coarse, list(yaws), workers)]


def _coarse_from(objective: _Objective, yaw: float, *, placement, pose) -> tuple:
    """`_coarse` from the soles at ``yaw`` [deg] (in the driver or a worker: `_coarse_starts`)."""
    return _coarse(objective, yaw, "soles", placement, pose)


def fit_body(
    scan_points: torch.Tensor | np.ndarray,
    body: BodyModel | None = None,
    *,
    anny_model=None,
    config: BodyFitConfig | None = None,
    floor_y: float | None = None,
    workers: int = 1,
) -> BodyFitResult:
    """Fit Anny's shape, pose and placement to a full (possibly clothed) scan.

    Args:
        scan_points: (N, 3) scan points [m], world frame (Y up, the person roughly upright). Converted
            to float32 on the CPU for the fit.
        body: an optional float32 `BodyModel` (batch 1) to fit in place; else one is made from ``anny_model``.
        anny_model: a loaded Anny model to build the body from (saves the load time).
        config: a `BodyFitConfig`.
        floor_y: the height [m] of the floor the person stands on (the intake puts the floor it removed at
            y = 0): the soles are held on it (``config.floor_weight``); None when the scan had none.
        workers: starting directions fitted at a time, in forked processes (`forked`; one core each); the
            same result for any number.

    Returns:
        a `BodyFitResult` with the fitted body and its residual.

    Raises:
        ScanError: on fewer than 100 points, NaNs or a wrong shape.
    """
    cfg = config or BodyFitConfig()
    t0 = time.perf_counter()
    scan_all = torch.as_tensor(np.asarray(scan_points) if not torch.is_tensor(scan_points) else scan_points)
    scan_all = scan_all.detach().to(device="cpu", dtype=torch.float32)
    _check_scan(scan_all)
    if body is None:
        body = BodyModel(anny_model=anny_model, dtype=torch.float32)
    if body.batch_size != 1:
        raise ValueError(f"fit_body fits one body; got a BodyModel with batch size {body.batch_size}")
    rng = np.random.default_rng(cfg.seed)
    if scan_all.shape[0] > cfg.max_scan_points:
        keep = torch.from_numpy(rng.choice(scan_all.shape[0], cfg.max_scan_points, replace=False))
        scan = scan_all[keep]
    else:
        scan = scan_all
    objective = _Objective(body, scan, cfg, floor_y)
    placement = [
        {"params": [body.global_orient], "lr": cfg.lr_rotation},
        {"params": [body.translation], "lr": cfg.lr_translation},
    ]
    pose = [{"params": [body.pose], "lr": cfg.lr_pose}]
    soles = _coarse_starts(objective, _yaw_starts(scan, cfg), placement, pose, workers)
    placed = [min(soles, key=lambda p: p[0])]  # the yaw whose coarse result scores lowest (`_coarse`)
    # a scan that shows the feet stands on its lowest point: the head start is for scans cut above them
    # (it lost on 14 of 15 complete scans, docs/BENCHMARKS.md), at the yaw chosen, and chosen or not by
    # the pose stage's loss as it was measured
    if cfg.head_start and not shows_feet(scan.numpy()):
        placed.append(_coarse(objective, placed[0][2], "head", placement, pose))
    _, losses, yaw, start, state = min(placed, key=lambda p: p[1]["pose"])
    body.load_state_dict(state)
    losses.update({f"pose_{s}": stage["pose"] for _, stage, _, s, _ in placed})
    objective.final = True
    params = [body.global_orient, body.translation, body.pose, body.phenotype_logits]
    losses["final"] = _run_icp(objective, params, cfg.final_rounds, cfg.final_iters)
    with torch.no_grad():
        verts = body().vertices[0]
        d_sb = torch.from_numpy(nearest_indices(scan_all, verts))
        d_sb = (scan_all - verts[d_sb]).norm(dim=-1).mean()
        d_bs = torch.from_numpy(nearest_indices(verts, scan_all))
        d_bs = (verts - scan_all[d_bs]).norm(dim=-1).mean()
        height = float(body.standing_height()[0])
    return BodyFitResult(
        body=body,
        chamfer_m=float(0.5 * (d_sb + d_bs)),
        height_m=height,
        seconds=time.perf_counter() - t0,
        yaw_deg=yaw,
        start=start,
        losses=losses,
    )
