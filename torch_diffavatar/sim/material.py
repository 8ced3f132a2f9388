"""Cloth material parameters (SI units) and the documented default, a medium-weight woven cotton."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch


@dataclass(frozen=True)
class ClothMaterial:
    """Orthotropic membrane + bending material of a woven fabric (paper §3.2, appendix A).

    Any field may be a Python float or a 0-dim tensor (e.g. a bending stiffness being optimised);
    the rest-data functions in `sim/constraints.py` are differentiable in the tensor fields.

    Attributes:
        areal_density: mass per rest area [kg/m²].
        k_uu: membrane stretch stiffness along the pattern's u axis (warp) [N/m].
        k_vv: membrane stretch stiffness along v (weft) [N/m].
        k_uv: in-plane shear stiffness [N/m]; energy density ``2 k_uv E01²`` (= ½ k_uv γ², γ = 2 E01).
        poisson: Poisson-like coupling ν ∈ [0, 1): coupling term ``ν sqrt(k_uu k_vv) E00 E11``.
        bend_stiffness: bending stiffness k_b [N·m] of the discrete-shell energy
            ``½ k_b · 3|ē|²/(Ā1+Ā2) · (θ − θ̄)²`` per interior edge.
        damping: velocity damping rate [1/s]; each substep multiplies v by ``exp(−damping·dt)``.
        friction: Coulomb friction coefficient cloth–body [-].
        thickness: collision thickness [m]: cloth vertices are kept this far outside the body.

    Energy density per rest area: ``ψ = ½ Cᵀ K C`` with ``C = [E00, E11, E01]`` and
    ``K = [[k_uu, ν√(k_uu k_vv), 0], [ν√(k_uu k_vv), k_vv, 0], [0, 0, 4 k_uv]]``.
    """

    areal_density: float | torch.Tensor = 0.15
    k_uu: float | torch.Tensor = 2.0e4
    k_vv: float | torch.Tensor = 1.5e4
    k_uv: float | torch.Tensor = 1.0e3
    poisson: float | torch.Tensor = 0.0
    bend_stiffness: float | torch.Tensor = 5.0e-6
    damping: float | torch.Tensor = 0.5
    friction: float | torch.Tensor = 0.4
    thickness: float | torch.Tensor = 0.003

    def __post_init__(self):
        # values read detached: a field being fitted requires grad, and float() of it warns
        value = {f.name: _float(getattr(self, f.name)) for f in fields(self)}
        for name, v in value.items():
            if v != v or v < 0:
                raise ValueError(f"ClothMaterial.{name} must be finite and >= 0, got {v}")
        if value["poisson"] >= 1.0:
            raise ValueError(f"ClothMaterial.poisson must be < 1, got {value['poisson']:g}")
        for name in ("areal_density", "k_uu", "k_vv", "k_uv"):
            if value[name] <= 0:
                raise ValueError(f"ClothMaterial.{name} must be > 0, got {value[name]}")


def uniaxial_stiffness(material: ClothMaterial) -> float:
    """How stiff a strip of ``material`` is when pulled along one axis with its width free [N/m]: the
    geometric mean over u and v of ``k − c²/k'`` (c = ν√(k_uu k_vv), the coupling; ``k`` when ν = 0).

    What a hanging panel feels, and so what "stretch" compares between two materials; for Newton's
    isotropic membrane in our units (`sim.newton_units.membrane_from_newton`) it is ``(λ+2μ)(1 − ν²)``.
    """
    kuu, kvv, nu = (_float(getattr(material, k)) for k in ("k_uu", "k_vv", "poisson"))
    coupling_sq = nu * nu * kuu * kvv
    return float(((kuu - coupling_sq / kvv) * (kvv - coupling_sq / kuu)) ** 0.5)


def _float(value: float | torch.Tensor) -> float:
    return float(value.detach()) if isinstance(value, torch.Tensor) else float(value)


def medium_cotton() -> ClothMaterial:
    """A medium-weight woven cotton (shirting / light poplin, ~150 g/m²).

    Reasoning behind each value (orders of magnitude; real fabrics vary by ±2–3×):

    * areal density 0.15 kg/m²: 150 gsm, a typical shirt/dress cotton (light 100, denim 300–400).
    * stretch k_uu = 2·10⁴, k_vv = 1.5·10⁴ N/m: Kawabata (KES-FB1) tensile tests of cotton shirtings give
      initial tensile moduli of a few 10⁴ N/m per unit width at small strain; the weft is usually a
      little softer than the warp. Gravity on a 1 m drop (≈1.5 N/m) then strains the cloth < 0.1 %.
    * shear k_uv = 10³ N/m: woven fabrics shear far more easily than they stretch (KES shear rigidity
      G ≈ 0.5–2 gf/cm/deg ≈ 0.3–1·10³ N/m per radian).
    * bending k_b = 5·10⁻⁶ N·m: KES bending rigidity B of cotton shirting ≈ 0.03–0.1 gf·cm²/cm
      (1 gf·cm²/cm = 9.81·10⁻⁵ N·m), i.e. 3·10⁻⁶ – 10⁻⁵ N·m.
    * damping 0.5 1/s: mild numerical air drag; it changes the path, not the rest shape.
    * friction 0.4: cotton on skin / cotton on cotton measured ≈ 0.3–0.6.
    * thickness 3 mm: collision offset (real cloth ≈ 0.3–0.5 mm) large enough to keep the cloth visibly
      outside a body mesh whose triangles are ~1 cm.
    """
    return ClothMaterial()
