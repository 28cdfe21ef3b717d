"""Rotation conversions in pure PyTorch (batched, differentiable).

Conventions (DESIGN §2, reference §6):
* 6D = the first two ROWS of the rotation matrix, row-major (pytorch3d
  ``matrix_to_rotation_6d``); Gram-Schmidt rebuilds the rows.
* Axis-angle -> matrix is the standard Rodrigues formula (``smplx.lbs.batch_rodrigues``),
  a column-vector rotation ``v' = R v``.
* Quaternions are (w, x, y, z), unit, with w >= 0.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

_EPS = 1e-8


def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """(..., 3) axis-angle -> (..., 3, 3). Exact near zero through a Taylor branch."""
    theta2 = (aa * aa).sum(-1, keepdim=True)
    theta = torch.sqrt(theta2.clamp_min(_EPS * _EPS))
    small = theta2 < 1e-12
    # sin(t)/t and (1-cos t)/t^2 with series for tiny angles so gradients stay finite.
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / (theta * theta))
    x, y, z = aa.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*aa.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(k)
    return eye + a[..., None] * k + b[..., None] * (k @ k)


def matrix_to_quaternion(m: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 4) unit quaternion (w, x, y, z) with w >= 0 (Shepperd's method)."""
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # Four candidate solutions; pick the numerically best (largest denominator) per element.
    q_abs = torch.sqrt(
        torch.stack(
            [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1
        ).clamp_min(0.0)
    )
    cands = torch.stack(
        [
            torch.stack([q_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, q_abs[..., 1] ** 2, m10 + m01, m02 + m20], -1),
            torch.stack([m02 - m20, m10 + m01, q_abs[..., 2] ** 2, m12 + m21], -1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, q_abs[..., 3] ** 2], -1),
        ],
        -2,
    )
    cands = cands / (2.0 * q_abs[..., None].clamp_min(0.1))
    idx = q_abs.argmax(-1)
    q = torch.gather(cands, -2, idx[..., None, None].expand(*idx.shape, 1, 4)).squeeze(-2)
    q = F.normalize(q, dim=-1)
    return torch.where(q[..., :1] < 0, -q, q)


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) (w, x, y, z) -> (..., 3, 3)."""
    w, x, y, z = F.normalize(q, dim=-1).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(*q.shape[:-1], 3, 3)


def matrix_to_axis_angle(m: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 3) axis-angle with angle in [0, pi]; via the quaternion for stability."""
    q = matrix_to_quaternion(m)
    v = q[..., 1:]
    s = v.norm(dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(s, q[..., :1])
    scale = torch.where(s < 1e-8, 2.0 + torch.zeros_like(s), angle / s.clamp_min(1e-12))
    return v * scale


def matrix_to_rotation_6d(m: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 6): first two rows, row-major (pytorch3d)."""
    return m[..., :2, :].reshape(*m.shape[:-2], 6)


def rotation_6d_to_matrix(d6: torch.Tensor) -> torch.Tensor:
    """(..., 6) -> (..., 3, 3) by Gram-Schmidt; the b's are ROWS (pytorch3d)."""
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = F.normalize(a1, dim=-1)
    b2 = F.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
    b3 = torch.cross(b1, b2, dim=-1)
    return torch.stack((b1, b2, b3), dim=-2)


def quaternion_slerp(q0: torch.Tensor, q1: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Shortest-arc slerp of unit quaternions; t broadcasts against (...,)."""
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    dot = dot.abs().clamp(max=1.0)
    t = t[..., None] if t.dim() == q0.dim() - 1 else t
    omega = torch.acos(dot)
    so = torch.sin(omega)
    lin = so < 1e-6
    w0 = torch.where(lin, 1.0 - t, torch.sin((1.0 - t) * omega) / so.clamp_min(1e-12))
    w1 = torch.where(lin, t, torch.sin(t * omega) / so.clamp_min(1e-12))
    return F.normalize(w0 * q0 + w1 * q1, dim=-1)


def rot_x(angle: torch.Tensor) -> torch.Tensor:
    return _axis_rot(angle, 0)


def rot_y(angle: torch.Tensor) -> torch.Tensor:
    return _axis_rot(angle, 1)


def rot_z(angle: torch.Tensor) -> torch.Tensor:
    return _axis_rot(angle, 2)


def _axis_rot(angle: torch.Tensor, axis: int) -> torch.Tensor:
    angle = torch.as_tensor(angle)
    aa = torch.zeros(*angle.shape, 3, dtype=angle.dtype if angle.is_floating_point() else torch.float64)
    aa[..., axis] = angle
    return axis_angle_to_matrix(aa)
