"""PointNetLK's network in CPU torch (Aoki, Goforth, Srivatsan & Lucey, "PointNetLK: Robust &
Efficient Point Cloud Registration using PointNet", CVPR 2019), laid out so that learning3d's
pretrained state (``pointnetlk/best_model.t7``: ``dt`` and ``feature_model.*``) loads into it with
``strict=True``. Written from the paper; imported only by :mod:`esmicp_lab.baselines.pointnetlk`, which
imports torch lazily.

- **Features.** PointNet without its input/feature transform nets: five shared per-point layers
  (1x1 convolutions 3-64-64-64-128-1024, each followed by batch norm and ReLU), then a max over the
  points: a 1,024-vector ``phi(P)``.
- **Inverse-compositional Lucas-Kanade on SE(3).** With the template (target) ``T`` and the source
  ``S``, both centred on their own centroids: the Jacobian of the template's features in the six
  twist directions is taken once, by finite differences,
  ``J_k = (phi(T) - phi(exp(-dt_k xi_k) T)) / dt_k`` (``dt`` is part of the trained state, 0.01);
  then each iteration computes the residual ``r = phi(g S) - phi(T)``, the increment
  ``dx = -pinv(J) r`` and updates ``g <- exp(dx) g``, until ``|dx| < xtol`` or the iteration
  budget runs out. Twists are ``(rotation, translation)``; ``exp`` is the matrix exponential of the
  4x4 twist matrix. ``g`` maps the centred source onto the centred template.
"""

from __future__ import annotations

import torch
from torch import nn

#: Widths of PointNet's shared per-point layers (the pretrained state's).
LAYER_WIDTHS = (64, 64, 64, 128, 1024)


class PointNetFeatures(nn.Module):
    """``(B, N, 3)`` points -> ``(B, 1024)`` max-pooled PointNet features."""

    def __init__(self):
        super().__init__()
        widths = (3,) + LAYER_WIDTHS
        for index in range(len(LAYER_WIDTHS)):
            setattr(self, f"conv{index + 1}", nn.Conv1d(widths[index], widths[index + 1], 1))
            setattr(self, f"bn{index + 1}", nn.BatchNorm1d(widths[index + 1]))

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        x = points.transpose(1, 2)
        for index in range(1, len(LAYER_WIDTHS) + 1):
            x = torch.relu(getattr(self, f"bn{index}")(getattr(self, f"conv{index}")(x)))
        return x.max(dim=2).values


def twist_exp(twist: torch.Tensor) -> torch.Tensor:
    """``(..., 6)`` twists ``(w, v)`` -> ``(..., 4, 4)`` rigid transforms ``exp([w]_x, v)``."""
    w, v = twist[..., :3], twist[..., 3:]
    zero = torch.zeros_like(w[..., 0])
    matrix = torch.stack(
        [
            torch.stack([zero, -w[..., 2], w[..., 1], v[..., 0]], dim=-1),
            torch.stack([w[..., 2], zero, -w[..., 0], v[..., 1]], dim=-1),
            torch.stack([-w[..., 1], w[..., 0], zero, v[..., 2]], dim=-1),
            torch.stack([zero, zero, zero, zero], dim=-1),
        ],
        dim=-2,
    )
    return torch.linalg.matrix_exp(matrix)


def transform(g: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``points @ R.T + t`` for ``g`` ``(..., 4, 4)`` broadcast against ``points`` ``(..., N, 3)``."""
    return points @ g[..., :3, :3].transpose(-1, -2) + g[..., None, :3, 3]


class PointNetLK(nn.Module):
    """PointNet features + inverse-compositional LK; see the module's docstring."""

    def __init__(self, delta: float = 1e-2):
        super().__init__()
        self.feature_model = PointNetFeatures()
        self.dt = nn.Parameter(torch.full((1, 6), float(delta)), requires_grad=False)

    @torch.no_grad()
    def register(self, template: torch.Tensor, source: torch.Tensor, max_iterations: int, xtol: float = 1e-7):
        """``template`` ``(1, N, 3)``, ``source`` ``(1, M, 3)``, both centred.

        Returns ``(g, iterations, converged)``: ``g`` ``(4, 4)`` maps the source onto the template.
        """
        features_template = self.feature_model(template)  # (1, K)
        dt = self.dt[0]
        perturbations = twist_exp(torch.diag(-dt))  # (6, 4, 4)
        perturbed = transform(perturbations, template.expand(6, -1, -1))  # (6, N, 3)
        jacobian = ((features_template - self.feature_model(perturbed)) / dt[:, None]).T  # (K, 6)
        pseudo_inverse = torch.linalg.pinv(jacobian)  # (6, K)
        g = torch.eye(4, dtype=template.dtype)
        converged = False
        iterations = 0
        for iterations in range(1, max_iterations + 1):
            residual = self.feature_model(transform(g, source)) - features_template  # (1, K)
            dx = -(pseudo_inverse @ residual[0])
            if float(dx.norm()) < xtol:
                converged = True
                break
            g = twist_exp(dx) @ g
        return g, iterations, converged
