"""Motion models of the particle filter: :class:`OdometryMotionModel` (odometry increments
with Gaussian noise in the tangent space, SE(2) and SE(3))."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
from jaxtyping import Array, Float, PRNGKeyArray

from ..rays import is_concrete
from ._poses import Pose, dof, from_vector

# --------------------------------------------------------------------------------------
# Motion model
# --------------------------------------------------------------------------------------


class OdometryMotionModel(eqx.Module):
    """Odometry motion model of Sec. 12.4.3: ``X_t = X_{t-1} transform(xi)``,
    ``xi ~ N(chi, Sigma)`` in the robot frame, ``chi`` the relative odometry.

    ``Sigma`` is diagonal with standard deviations
    ``inflation * (sigma + alpha @ |chi|)``: a constant part plus a part proportional to
    the magnitude of the motion (e.g. ``alpha[2, 0]`` adds heading noise per metre
    driven). (The dissertation writes ``transform(xi) X_{t-1}`` for its matrix convention;
    here poses are world-from-robot, so the robot-frame increment multiplies on the right.)

    Attributes:
        sigma: ``[k]`` constant standard deviations per step (m, rad).
        alpha: ``[k k]`` proportional standard deviations (per m or rad of ``|chi_j|``).
        inflation: factor on all standard deviations (the "inflated noise" of Sec. 12.4.3).
        group: ``jaxlie.SE2`` (k = 3) or ``jaxlie.SE3`` (k = 6).
    """

    sigma: Float[Array, " k"]
    alpha: Float[Array, "k k"]
    inflation: Float[Array, ""]
    group: type = eqx.field(static=True)

    def __init__(self, sigma, alpha=None, inflation: float = 1.0, group: type = jaxlie.SE2):
        k = dof(group)
        self.group = group
        self.sigma = jnp.asarray(sigma, dtype=jnp.result_type(float))
        self.alpha = (
            jnp.zeros((k, k), self.sigma.dtype)
            if alpha is None
            else jnp.asarray(alpha, self.sigma.dtype)
        )
        self.inflation = jnp.asarray(inflation, self.sigma.dtype)
        if self.sigma.shape != (k,) or self.alpha.shape != (k, k) or self.inflation.shape != ():
            raise ValueError(
                f"sigma must be [{k}], alpha [{k} {k}] and inflation a scalar for "
                f"{group.__name__}; got {self.sigma.shape}, {self.alpha.shape}, "
                f"{self.inflation.shape}"
            )
        for name, x in (
            ("sigma", self.sigma),
            ("alpha", self.alpha),
            ("inflation", self.inflation),
        ):
            if is_concrete(x) and not bool(jnp.all((x >= 0) & jnp.isfinite(x))):
                raise ValueError(f"{name} must be finite and >= 0")

    def std(self, control: Float[Array, " k"]) -> Float[Array, " k"]:
        """Standard deviations of ``xi`` for the control ``chi``."""
        return self.inflation * (self.sigma + self.alpha @ jnp.abs(control))

    def __call__(self, particles: Pose, control: Float[Array, " k"], *, key: PRNGKeyArray) -> Pose:
        n = particles.parameters().shape[0]
        k = dof(self.group)
        dtype = particles.parameters().dtype
        control = jnp.asarray(control, dtype)
        xi = control + self.std(control).astype(dtype) * jax.random.normal(key, (n, k), dtype)
        return particles @ from_vector(xi, self.group)
