"""Pose vectors <-> jaxlie groups and weighted pose means for SE(2) and SE(3) particles.

Pose vectors: SE(2) ``(x, y, theta)`` (m, m, rad); SE(3) ``(x, y, z, roll, pitch, yaw)``
(m, rad; ``R = Rz(yaw) Ry(pitch) Rx(roll)``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
from jaxtyping import Array, ArrayLike, Float

Pose = jaxlie.SE2 | jaxlie.SE3


def dof(group: type) -> int:
    """Length of the pose vector of ``group`` (3 for SE(2), 6 for SE(3))."""
    if group is jaxlie.SE2:
        return 3
    if group is jaxlie.SE3:
        return 6
    raise ValueError(f"pose group must be jaxlie.SE2 or jaxlie.SE3, got {group!r}")


def from_vector(v: Float[ArrayLike, "*b k"], group: type = jaxlie.SE2) -> Pose:
    """Pose group elements from pose vectors ``[*b 3]`` (SE2) or ``[*b 6]`` (SE3)."""
    v = jnp.asarray(v, dtype=jnp.result_type(float))
    k = dof(group)
    if v.shape[-1:] != (k,):
        raise ValueError(
            f"pose vectors for {group.__name__} must have shape [..., {k}], got {v.shape}"
        )
    if group is jaxlie.SE2:
        return jaxlie.SE2.from_xy_theta(v[..., 0], v[..., 1], v[..., 2])
    rot = jaxlie.SO3.from_rpy_radians(v[..., 3], v[..., 4], v[..., 5])
    return jaxlie.SE3.from_rotation_and_translation(rot, v[..., :3])


def to_vector(pose: Pose) -> Float[Array, "*b k"]:
    """Pose vectors of group elements (angles in ``(-pi, pi]``)."""
    if isinstance(pose, jaxlie.SE2):
        t = pose.translation()
        return jnp.concatenate([t, pose.rotation().as_radians()[..., None]], axis=-1)
    if isinstance(pose, jaxlie.SE3):
        rot = pose.rotation()
        rpy = jnp.stack(
            [rot.compute_roll_radians(), rot.compute_pitch_radians(), rot.compute_yaw_radians()],
            axis=-1,
        )
        return jnp.concatenate([pose.translation(), rpy], axis=-1)
    raise ValueError(f"pose must be a jaxlie.SE2 or jaxlie.SE3, got {type(pose).__name__}")


def circular_mean(
    angles: Float[Array, "*b n"], weights: Float[Array, "*b n"]
) -> Float[Array, "*b"]:
    """Weighted circular mean ``atan2(sum w sin a, sum w cos a)`` (rad) over the last axis."""
    return jnp.arctan2(
        jnp.sum(weights * jnp.sin(angles), -1), jnp.sum(weights * jnp.cos(angles), -1)
    )


def weighted_mean(poses: Pose, weights: Float[Array, " n"]) -> Pose:
    """Weighted mean of ``[n]`` poses: arithmetic mean of the translations and, for SE(2),
    the circular mean of the headings; for SE(3) the normalised weighted sum of the unit
    quaternions after aligning their signs with the heaviest one (chordal L2 mean).

    ``weights`` need not be normalised (must be ``>= 0`` with a positive sum).
    """
    w = weights / jnp.sum(weights)
    t = jnp.sum(w[:, None] * poses.translation(), axis=0)
    if isinstance(poses, jaxlie.SE2):
        theta = circular_mean(poses.rotation().as_radians(), w)
        return jaxlie.SE2.from_rotation_and_translation(jaxlie.SO2.from_radians(theta), t)
    q = poses.rotation().wxyz
    ref = q[jnp.argmax(w)]
    q = q * jnp.where(q @ ref < 0, -1.0, 1.0)[:, None]
    qm = jnp.sum(w[:, None] * q, axis=0)
    qm = qm / jnp.linalg.norm(qm)
    return jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3(qm), t)


def take(poses: Pose, idx) -> Pose:
    """``poses[idx]`` for a batched group element."""
    return jax.tree.map(lambda x: x[idx], poses)


def relative_motion(
    poses: Float[ArrayLike, "t k"], group: type = jaxlie.SE2
) -> Float[Array, "t-1 k"]:
    """Relative motions ``X_{t-1}^{-1} X_t`` between consecutive pose vectors, expressed
    as pose vectors in the frame of ``X_{t-1}`` (the odometry control ``chi`` of Sec. 12.4.3).
    """
    g = from_vector(poses, group)
    prev, nxt = take(g, slice(None, -1)), take(g, slice(1, None))
    return to_vector(prev.inverse() @ nxt)
