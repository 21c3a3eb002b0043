"""Batched, differentiable Lie-group kernels: SO(2), SO(3), SE(2), SE(3) and R^n.

Every function works on tensors with any leading (batch) dimensions, in float32 or
float64, on the device of its inputs, and is differentiable with finite gradients
everywhere on the group, including exactly at the identity (angle 0) and at angle pi.

Representations
  - SO(2): 2x2 rotation matrices; tangent vectors have shape (..., 1).
  - SO(3): 3x3 rotation matrices; tangent (..., 3) = (wx, wy, wz) in the paper's basis
    E1, E2, E3 (rotations about x, y, z): hat(w) = [[0, -wz, wy], [wz, 0, -wx], [-wy, wx, 0]].
  - SE(2): 3x3 homogeneous matrices [[R, t], [0, 1]]; tangent (..., 3) = (omega, vx, vy).
  - SE(3): 4x4 homogeneous matrices [[R, t], [0, 1]]; tangent (..., 6) = (wx, wy, wz, vx, vy, vz),
    rotation first as in the paper (E1..E3 rotations, E4..E6 translations).
  - R^n: group elements are plain vectors (..., n), tangent vectors too (any trailing n);
    exp/log are the identity and compose is addition. ``Rn.dim`` is ``None`` (any n);
    an instance ``Rn(n)`` carries ``dim == n`` for code that needs a number.

All exponentials and logarithms are closed forms (cos/sin, Rodrigues, V-matrices), never
``torch.linalg.matrix_exp``. Coefficients such as sin(theta)/theta are evaluated from
theta^2 with a Taylor polynomial (4 terms, truncation error far below the dtype's epsilon)
when theta is below a dtype-dependent threshold (theta < 0.1 in float32, theta < 1e-2 in
float64), and with the "double where" pattern: the closed-form branch sees
``theta2_safe = where(small, 1, theta2)``, so it never produces inf/NaN values or gradients
that the masked-out branch could leak into the backward pass.

The SO(3) logarithm goes through a unit quaternion obtained by Shepperd's method (the
largest of the four diagonal-based candidates is used, so every square root has an
argument >= 1) with w >= 0, then theta = 2 atan2(|xyz|, w). This is accurate at small
angles and at pi alike; at exactly pi the axis sign is arbitrary (both are valid logs).

Quaternions are (w, x, y, z), scalar first, as in MuJoCo observations.

Every group is a subclass of :class:`LieGroup` (the protocol: ``exp``, ``log``, ``compose``, ``inverse``, ``hat``,
``vee``, ``identity``, ``dim``, ``matrix_size``), used through the class itself (``SO3.exp(v)``), as in LieTorch /
PyPose; the matrix groups share ``compose`` (matrix product) and ``identity`` through :class:`MatrixLieGroup`.
"""

from gem_head.lie.base import LieGroup, MatrixLieGroup
from gem_head.lie.kernels import small_angle_threshold
from gem_head.lie.rn import Rn
from gem_head.lie.se import SE2, SE3
from gem_head.lie.so2 import SO2, wrap_angle
from gem_head.lie.so3 import SO3

__all__ = ["LieGroup", "MatrixLieGroup", "SO2", "SO3", "SE2", "SE3", "Rn", "small_angle_threshold", "wrap_angle"]
