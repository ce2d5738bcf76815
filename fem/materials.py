"""Hyperelastic material laws written in the invariants (I1, I2, J) of F.

Every law supplies its strain energy's partial derivatives with respect to the
invariants ``I1 = tr C``, ``I2 = (I1^2 - tr C^2) / 2`` and ``J = det F``; the
kinematics module turns them into the first Piola-Kirchhoff stress and its
consistent tangent for any law. The volumetric part ``U(J) = kappa/2 G(J)^2`` is
kept apart so that the mixed (u-p) formulations can replace it by a pressure field.

Conventions follow the dissertation: the neo-Hookean law is
``W = c1 (I1bar - 3) + U(J)``, so the small-strain shear modulus is ``2 c1``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

__all__ = [
    "FebioNeoHookean",
    "Material",
    "MooneyRivlin",
    "NeoHookean",
    "Volumetric",
    "bulk_modulus_from_poisson",
]

VolumetricKind = Literal["quadratic", "log"]


def bulk_modulus_from_poisson(shear_modulus_pa: float, nu: float) -> float:
    """Bulk modulus from the shear modulus and Poisson's ratio (small strain).

    Parameters
    ----------
    shear_modulus_pa : float
        Small-strain shear modulus mu in Pa.
    nu : float
        Poisson's ratio, ``-1 < nu < 0.5``.

    Returns
    -------
    float
        ``kappa = 2 mu (1 + nu) / (3 (1 - 2 nu))`` in Pa.
    """
    if not -1.0 < nu < 0.5:
        raise ValueError(f"Poisson's ratio must lie in (-1, 0.5), got nu={nu}")
    return 2.0 * shear_modulus_pa * (1.0 + nu) / (3.0 * (1.0 - 2.0 * nu))


@dataclass(frozen=True)
class Volumetric:
    """Volumetric energy ``U(J) = kappa/2 G(J)^2``.

    Parameters
    ----------
    kappa_pa : float
        Bulk modulus in Pa.
    kind : {"quadratic", "log"}
        ``G = J - 1`` (quadratic) or ``G = ln J`` (log).
    """

    kappa_pa: float
    kind: VolumetricKind = "quadratic"

    def __post_init__(self) -> None:
        if not self.kappa_pa > 0:
            raise ValueError(f"bulk modulus must be positive, got {self.kappa_pa} Pa")
        if self.kind not in ("quadratic", "log"):
            raise ValueError(f"volumetric kind must be 'quadratic' or 'log', got {self.kind!r}")

    def g(self, J: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return ``G(J)``, ``G'(J)`` and ``G''(J)``."""
        if self.kind == "quadratic":
            return J - 1.0, np.ones_like(J), np.zeros_like(J)
        return np.log(J), 1.0 / J, -1.0 / J**2


class Material(Protocol):
    """What the assembler needs from a material law."""

    volumetric: Volumetric

    @property
    def shear_modulus_pa(self) -> float:
        """Small-strain shear modulus in Pa."""
        ...

    def partials(
        self, I1: np.ndarray, I2: np.ndarray, J: np.ndarray
    ) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
        """First and second partials of the non-volumetric energy.

        Returns ``(W1, W2, WJ)`` and ``(W11, W12, W1J, W22, W2J, WJJ)``.
        """
        ...


def _volumetric(shear_pa: float, bulk_pa: float | None, nu: float | None, kind) -> Volumetric:
    if (bulk_pa is None) == (nu is None):
        raise ValueError("give exactly one of bulk_pa or nu")
    kappa = bulk_pa if bulk_pa is not None else bulk_modulus_from_poisson(shear_pa, nu)
    return Volumetric(kappa_pa=float(kappa), kind=kind)


def _positive(name: str, value: float) -> None:
    if not value > 0:
        raise ValueError(f"{name} must be positive, got {value}")


@dataclass(frozen=True)
class MooneyRivlin:
    """Uncoupled Mooney-Rivlin: ``W = c1 (I1bar - 3) + c2 (I2bar - 3) + U(J)``.

    Parameters
    ----------
    c1_pa, c2_pa : float
        Material constants in Pa (``c1 > 0``, ``c2 >= 0``); shear modulus ``2 (c1 + c2)``.
    volumetric : Volumetric
        The volumetric energy.
    """

    c1_pa: float
    c2_pa: float
    volumetric: Volumetric

    def __post_init__(self) -> None:
        _positive("c1_pa", self.c1_pa)
        if self.c2_pa < 0:
            raise ValueError(f"c2_pa must be non-negative, got {self.c2_pa}")

    @classmethod
    def from_poisson(
        cls, c1_pa: float, c2_pa: float, nu: float, *, kind: VolumetricKind = "quadratic"
    ) -> MooneyRivlin:
        """Build from ``c1``, ``c2`` and a small-strain Poisson ratio."""
        _positive("c1_pa", c1_pa)
        return cls(c1_pa, c2_pa, _volumetric(2.0 * (c1_pa + c2_pa), None, nu, kind))

    @property
    def shear_modulus_pa(self) -> float:
        """Small-strain shear modulus ``2 (c1 + c2)`` in Pa."""
        return 2.0 * (self.c1_pa + self.c2_pa)

    def partials(self, I1, I2, J):
        """Partials of ``c1 (J^-2/3 I1 - 3) + c2 (J^-4/3 I2 - 3)``."""
        c1, c2 = self.c1_pa, self.c2_pa
        j23, j43 = J ** (-2.0 / 3.0), J ** (-4.0 / 3.0)
        zero = np.zeros_like(J)
        W1 = c1 * j23
        W2 = c2 * j43 + zero
        WJ = -2.0 / 3.0 * c1 * j23 / J * I1 - 4.0 / 3.0 * c2 * j43 / J * I2
        W1J = -2.0 / 3.0 * c1 * j23 / J
        W2J = -4.0 / 3.0 * c2 * j43 / J
        WJJ = 10.0 / 9.0 * c1 * j23 / J**2 * I1 + 28.0 / 9.0 * c2 * j43 / J**2 * I2
        return (W1, W2, WJ), (zero, zero, W1J, zero, W2J, WJJ)


def NeoHookean(
    c1_pa: float,
    *,
    nu: float | None = None,
    bulk_pa: float | None = None,
    kind: VolumetricKind = "quadratic",
) -> MooneyRivlin:
    """Uncoupled neo-Hookean ``W = c1 (I1bar - 3) + U(J)`` (shear modulus ``2 c1``).

    Parameters
    ----------
    c1_pa : float
        Material constant in Pa, ``c1 > 0``.
    nu, bulk_pa : float, optional
        Exactly one: small-strain Poisson ratio or bulk modulus in Pa.
    kind : {"quadratic", "log"}
        Volumetric function, ``kappa/2 (J-1)^2`` or ``kappa/2 (ln J)^2``.

    Returns
    -------
    MooneyRivlin
        A Mooney-Rivlin law with ``c2 = 0``.
    """
    _positive("c1_pa", c1_pa)
    return MooneyRivlin(c1_pa, 0.0, _volumetric(2.0 * c1_pa, bulk_pa, nu, kind))


@dataclass(frozen=True)
class FebioNeoHookean:
    """FEBio's coupled neo-Hookean ``W = mu/2 (I1-3) - mu ln J + lambda/2 (ln J)^2``.

    Parameters
    ----------
    E_pa : float
        Young's modulus in Pa.
    nu : float
        Poisson's ratio.
    """

    E_pa: float
    nu: float

    def __post_init__(self) -> None:
        _positive("E_pa", self.E_pa)
        if not -1.0 < self.nu < 0.5:
            raise ValueError(f"Poisson's ratio must lie in (-1, 0.5), got nu={self.nu}")

    @property
    def shear_modulus_pa(self) -> float:
        """Shear modulus ``mu = E / (2 (1 + nu))`` in Pa."""
        return self.E_pa / (2.0 * (1.0 + self.nu))

    @property
    def volumetric(self) -> Volumetric:
        """``lambda/2 (ln J)^2``, with the Lame constant as ``kappa``."""
        lam = self.E_pa * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))
        return Volumetric(kappa_pa=lam, kind="log")

    def partials(self, I1, I2, J):
        """Partials of ``mu/2 (I1 - 3) - mu ln J``."""
        mu = self.shear_modulus_pa
        zero = np.zeros_like(J)
        return (mu / 2.0 + zero, zero, -mu / J), (zero, zero, zero, zero, zero, mu / J**2)
