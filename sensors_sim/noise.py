r"""Every random law the emulators draw from, in one place.

Each process (a sensor, a jammer, the truth) draws only from its own generator,
``process_rng(seed, process_id, run) = Generator(PCG64(SeedSequence([seed, run,
crc32(process_id)])))``, so a distributed run (each process seeds itself; run 0) and an
in-process Monte Carlo run (``run = r``) draw the same numbers. The laws:

* white-noise jerk (the truth's process noise), per axis on ``[p, v, a]``:
  ``x_{k+1} = F x_k + w_k``, ``w_k ~ N(0, q·Q₁(dt))``, with
  ``F = [[1, dt, dt²/2], [0, 1, dt], [0, 0, 1]]`` and
  ``Q₁ = [[dt⁵/20, dt⁴/8, dt³/6], [dt⁴/8, dt³/3, dt²/2], [dt³/6, dt²/2, dt]]``
  (``fusion.motion.ConstantAcceleration``'s). ``q`` is the jerk's PSD (m²/s⁵), and
  ``q·Q₁(dt)`` is the exact discretisation: every n-th node of a grid of step ``dt`` has
  the law of a grid of step ``n·dt``;
* Gaussian measurement noise ``σ·n``, ``n ~ N(0, 1)``;
* outliers (jamming) of standard deviation ``σ₂``, from one ``u ~ U(0, 1)`` per component
  by the inverse CDF: ``laplacian`` with scale ``b = σ₂/√2``,
  ``x = −b·sgn(u − ½)·ln(1 − 2|u − ½|)``; ``uniform``, ``x = √3·σ₂·(2u − 1)``.

Drawing outliers from uniforms (rather than ``Generator.laplace``) consumes the same
variates every scan whichever law applies, which keeps the streams aligned.
"""

from __future__ import annotations

import zlib

import numpy as np

from fusion.motion import ConstantAcceleration

OUTLIER_LAWS = ("laplacian", "uniform")


def process_rng(seed: int, process_id: str, run: int = 0) -> np.random.Generator:
    """The generator of one process for one run: PCG64 seeded by
    ``SeedSequence([seed, run, crc32(process_id)])``, so a process draws the same numbers
    in a distributed run and in run ``run`` of the in-process evaluation."""
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative int, got {seed!r}")
    if not isinstance(run, (int, np.integer)) or run < 0:
        raise ValueError(f"run must be a non-negative int, got {run!r}")
    entropy = [int(seed), int(run), zlib.crc32(process_id.encode())]
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(entropy)))


# --- white-noise jerk ------------------------------------------------------------------


def jerk_deviation(rng: np.random.Generator, q: float, dt: float, steps: int) -> np.ndarray:
    """A white-noise-jerk path from zero: ``e_0 = 0``, ``e_{k+1} = F e_k + w_k``.

    Returns ``(steps + 1, 9)`` states in the layout ``[px py pz vx vy vz ax ay az]``.
    Consumes exactly ``steps·9`` standard normals (one ``(steps, 3, 3)`` call).
    """
    model = ConstantAcceleration(q)  # the trackers' CA model: the same F and Q₁
    F = model.F_axis(dt)
    L = np.linalg.cholesky(model.Q_axis(dt))
    w = rng.standard_normal((steps, 3, 3)) @ L.T  # [step, axis, (p, v, a)]
    e = np.zeros((steps + 1, 3, 3))
    for k in range(steps):
        e[k + 1] = e[k] @ F.T + w[k]
    # [step, axis, derivative] -> [step, derivative·3 + axis]
    return e.transpose(0, 2, 1).reshape(steps + 1, 9)


# --- measurement noise -----------------------------------------------------------------


def outlier_from_uniform(u: np.ndarray, std: float | np.ndarray, law: str) -> np.ndarray:
    """Outlier noise of standard deviation ``std`` from uniforms ``u`` (inverse CDF)."""
    u = np.asarray(u, dtype=float)
    if law == "laplacian":
        b = np.asarray(std) / np.sqrt(2.0)
        c = u - 0.5
        # 1 − 2|c| ∈ (0, 1] for u ∈ [0, 1); u = 0 exactly gives a finite tail value
        return -b * np.sign(c) * np.log(np.maximum(1.0 - 2.0 * np.abs(c), np.finfo(float).tiny))
    if law == "uniform":
        return np.sqrt(3.0) * np.asarray(std) * (2.0 * u - 1.0)
    raise ValueError(f"unknown outlier law {law!r}; expected one of {OUTLIER_LAWS}")


def outlier_cdf(x: np.ndarray, std: float, law: str) -> np.ndarray:
    """CDF of the outlier law (for tests and for documentation of the law)."""
    x = np.asarray(x, dtype=float)
    if law == "laplacian":
        b = std / np.sqrt(2.0)
        return np.where(x < 0, 0.5 * np.exp(x / b), 1.0 - 0.5 * np.exp(-x / b))
    if law == "uniform":
        a = np.sqrt(3.0) * std
        return np.clip((x + a) / (2.0 * a), 0.0, 1.0)
    raise ValueError(f"unknown outlier law {law!r}; expected one of {OUTLIER_LAWS}")


class ScanDraws:
    """The variates of one scan of one target, always drawn in the same pattern.

    Per scan and target an emulator draws, whatever happens next: ``detect`` and
    ``outlier`` (two uniforms, compared with P_D and the outlier probability),
    ``gauss`` (n standard normals) and ``law`` (n uniforms for the outlier law).
    Missed detections, coverage and jamming only change how the draws are *used*, so a
    sensor's stream is identical whether or not a jammer acts on it.
    """

    __slots__ = ("detect", "outlier", "gauss", "law")

    def __init__(self, rng: np.random.Generator, n: int):
        u = rng.random(2 + n)
        self.detect = float(u[0])
        self.outlier = float(u[1])
        self.law = u[2:]
        self.gauss = rng.standard_normal(n)

    @classmethod
    def rows(cls, rng: np.random.Generator, count: int, n: int) -> "ScanDraws":
        """The variates of ``count`` scans at once, as arrays with a row per scan: all the
        uniforms (``count × (2 + n)``), then all the normals (``count × n``). A rotating
        radar draws a turn's so (:mod:`sensors_sim.emulators`)."""
        out = cls.__new__(cls)
        u = rng.random((count, 2 + n))
        out.detect, out.outlier, out.law = u[:, 0], u[:, 1], u[:, 2:]
        out.gauss = rng.standard_normal((count, n))
        return out
