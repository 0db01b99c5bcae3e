"""Tools to trust a gradient: finite differences (also on Lie groups), a gradient checker
and a pytree comparison; the library's own tests use them.

- :func:`finite_difference` ``(f, x)``: central differences, structured like
  ``jax.jacobian(f)(x)`` for any pytree ``x``.
- :func:`manifold_finite_difference` / :func:`manifold_jacobian` ``(f, pose)``: the
  derivative of ``f(pose @ exp(delta))`` in the tangent vector ``delta`` at 0 (right
  perturbation, ``jaxlie.manifold.rplus``), by differences and by ``jax.jacfwd``;
  ``[*out, tangent_dim]``.
- :func:`check_gradients` ``(f, x)``: ``jacfwd == jacrev`` to near machine precision, both
  equal to finite differences, every derivative finite wherever ``f`` is; raises
  ``AssertionError`` naming the leaf, the errors and the worst entry, returns a
  :class:`GradientReport` otherwise. ``x`` may be a jaxlie pose (tangent-space check).
- :func:`tree_allclose` ``(a, b)``: same structure and ``np.allclose`` leaves.

Step size. Central differences err by ``h^2 |f'''| / 6`` (truncation) plus about
``eps_machine |f| / h`` (round-off), smallest near ``h ~ eps_machine^(1/3)`` times the
scale of ``x``. The default step is 1e-6 in float64 (relative accuracy ~1e-10 for
``|f| ~ |f'|``, well inside the default ``rtol = 1e-6``) and 1e-3 in float32 (~1e-4 at
best), scaled by ``max(1, |x_i|)`` so large coordinates are not stepped below their own
round-off; the derivative divides by the step actually representable in the dtype.

Why float64. In float32 a difference quotient keeps only 3-4 significant digits, so the
float32 tolerances (rtol 1e-2, atol 1e-3) can only catch gross errors (a missing factor,
a wrong sign, a 10 % error); subtle ones (a term of relative size 1e-4) need float64.
Enable it with ``jax.config.update("jax_enable_x64", True)`` before creating arrays.

Kinks. A finite difference across a kink or a jump of ``f`` (a ``max``, a ``clip``, a cell
boundary of an interpolant) is neither one-sided derivative; a failing check there means
"not smooth at ``x``", not necessarily a wrong gradient: compare the one-sided
differences (``method="forward"`` / ``"backward"``) with autodiff.

The finite differences loop over the input coordinates in Python (``2 n + 1`` calls of
``f`` with concrete arrays): these are testing tools for up to a few thousand
coordinates, not for production gradients.
"""

from ._gradcheck import Comparison as Comparison
from ._gradcheck import GradientReport as GradientReport
from ._gradcheck import check_gradients as check_gradients
from ._gradcheck import default_eps as default_eps
from ._gradcheck import default_tolerances as default_tolerances
from ._gradcheck import finite_difference as finite_difference
from ._gradcheck import manifold_finite_difference as manifold_finite_difference
from ._gradcheck import manifold_jacobian as manifold_jacobian
from ._gradcheck import tree_allclose as tree_allclose

__all__ = [
    "Comparison",
    "GradientReport",
    "check_gradients",
    "default_eps",
    "default_tolerances",
    "finite_difference",
    "manifold_finite_difference",
    "manifold_jacobian",
    "tree_allclose",
]
