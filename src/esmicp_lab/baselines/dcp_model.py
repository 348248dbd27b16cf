"""Deep Closest Point v1 in CPU torch (Wang & Solomon, "Deep Closest Point: Learning
Representations for Point Cloud Registration", ICCV 2019), laid out so that the authors' pretrained
state (``dcp/dcp_v1.t7``: ``emb_nn.conv1..conv5``, ``emb_nn.bn1..bn5`` and ``head.reflect``) loads
into it with ``strict=True``. Written from the paper, with the authors' code read for its
conventions only; imported only by :mod:`esmicp_lab.baselines.dcp`, which imports torch lazily.

- **Embedding (DGCNN, emb_dims 512).** For each point ``x_i`` of a ``(B, 3, N)`` cloud, its
  ``k = 20`` nearest neighbours ``x_j`` (in 3-D, the point itself included) give edge features
  ``[x_j, x_i]`` (6 channels: DCP concatenates the neighbour's coordinates with the point's, not
  their difference). Four 1x1 convolutions with batch norm and ReLU (6-64-64-128-256) run one
  after the other on the ``(B, C, N, k)`` edge tensor, and after each one the maximum over the
  ``k`` edges is kept; the four maxima (64 + 64 + 128 + 256 = 512 channels) go through a fifth
  1x1 convolution + batch norm + ReLU: a ``(B, 512, N)`` per-point embedding. The graph is built
  once, from the coordinates. Inference only: each 1x1 convolution and the batch norm after it
  (eval mode, its running statistics) are applied as one matrix product over the channels, on an
  edge tensor laid out ``(B, N, k, C)``: the same arithmetic as ``nn.Conv2d`` + ``nn.BatchNorm2d``
  up to float32 rounding, and faster on CPU, where torch runs these convolutions of a
  non-contiguous ``(B, C, N, k)`` tensor through its slow im2col path (docs/bench-paper.md, "Run
  time"; the modules are kept so that the state loads as the authors saved it).
- **Pointer: identity.** DCP adds the pointer's output to the embedding; v1's pointer returns the
  embedding itself, so every embedding is doubled before the head (this sets the softmax's
  temperature the weights were trained with).
- **SVD head.** Soft correspondences ``m(x_i) = sum_j softmax_j(<e_i, f_j> / sqrt(512)) y_j``
  of source point ``x_i`` among the target points ``y_j``; then the weighted Procrustes fit of
  the source onto them: ``H = sum_i (x_i - x_bar)(m_i - m_bar)^T = U S V^T``, ``R = V U^T``
  (``V diag(1, 1, -1) U^T`` when that has ``det < 0``; ``head.reflect`` is that diagonal), and
  ``t = m_bar - R x_bar``. So ``target ~= R source + t``: the model's ``(src, tgt)`` are our
  ``(source, target)`` and its ``(R_ab, t_ab)`` is ``T_target_source``.
"""

from __future__ import annotations

import math

import torch
from torch import nn

#: Neighbours per point in the edge convolution (the authors' setting).
K_NEIGHBOURS = 20

#: Width of the per-point embedding of the pretrained state.
EMB_DIMS = 512

#: Output widths of the four edge convolutions.
EDGE_WIDTHS = (64, 64, 128, 256)


def knn_indices(points: torch.Tensor, k: int) -> torch.Tensor:
    """``(B, 3, N)`` -> ``(B, N, k)`` indices of each point's ``k`` nearest points (itself included)."""
    squared = (points * points).sum(dim=1)  # (B, N)
    distances = squared[:, :, None] + squared[:, None, :] - 2.0 * points.transpose(1, 2) @ points
    return distances.topk(k, dim=-1, largest=False).indices


def edge_features(points: torch.Tensor, k: int) -> torch.Tensor:
    """``(B, 3, N)`` -> ``(B, N, k, 6)``: ``[neighbour, point]`` for each of the ``k`` edges."""
    batch, _, count = points.shape
    neighbours = knn_indices(points, min(k, count))  # (B, N, k)
    by_point = points.transpose(1, 2)  # (B, N, 3)
    gathered = by_point[torch.arange(batch)[:, None, None], neighbours]  # (B, N, k, 3)
    centre = by_point[:, :, None, :].expand_as(gathered)
    return torch.cat((gathered, centre), dim=3)


def _conv_bn_relu(x: torch.Tensor, conv: nn.Conv2d, norm: nn.BatchNorm2d) -> torch.Tensor:
    """ReLU(batch norm (1x1 convolution)) of a channels-last ``(..., C_in)`` tensor -> ``(..., C_out)``,
    the batch norm in eval mode (its running statistics) folded into the convolution's weights."""
    scale = norm.weight / torch.sqrt(norm.running_var + norm.eps)
    weight = conv.weight[:, :, 0, 0] * scale[:, None]
    return torch.relu(nn.functional.linear(x, weight, norm.bias - norm.running_mean * scale))


class DGCNNEmbedding(nn.Module):
    """``(B, 3, N)`` -> ``(B, 512, N)`` (see the module's docstring); inference only."""

    def __init__(self, emb_dims: int = EMB_DIMS, k: int = K_NEIGHBOURS):
        super().__init__()
        self.k = k
        widths = (6,) + EDGE_WIDTHS
        # Registered in the pretrained state's order: every convolution, then every batch norm.
        for index, (width_in, width_out) in enumerate(zip(widths[:-1], widths[1:]), start=1):
            setattr(self, f"conv{index}", nn.Conv2d(width_in, width_out, kernel_size=1, bias=False))
        self.conv5 = nn.Conv2d(sum(EDGE_WIDTHS), emb_dims, kernel_size=1, bias=False)
        for index, width in enumerate(EDGE_WIDTHS + (emb_dims,), start=1):
            setattr(self, f"bn{index}", nn.BatchNorm2d(width))

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        x = edge_features(points, self.k)  # (B, N, k, 6)
        maxima = []
        for index in range(1, len(EDGE_WIDTHS) + 1):
            x = _conv_bn_relu(x, getattr(self, f"conv{index}"), getattr(self, f"bn{index}"))
            maxima.append(x.max(dim=2).values)  # (B, N, C): the maximum over the k edges
        x = _conv_bn_relu(torch.cat(maxima, dim=2), self.conv5, self.bn5)  # (B, N, 512)
        return x.transpose(1, 2)


class SVDHead(nn.Module):
    """Soft correspondences + weighted Procrustes (see the module's docstring)."""

    def __init__(self):
        super().__init__()
        reflect = torch.eye(3)
        reflect[2, 2] = -1.0
        self.reflect = nn.Parameter(reflect, requires_grad=False)

    def forward(self, source_embedding, target_embedding, source, target):
        """Embeddings ``(B, D, N)`` / ``(B, D, M)``, clouds ``(B, 3, N)`` / ``(B, 3, M)`` ->
        ``R`` ``(B, 3, 3)``, ``t`` ``(B, 3)`` with ``target ~= R source + t``."""
        dims = source_embedding.shape[1]
        scores = torch.softmax(source_embedding.transpose(1, 2) @ target_embedding / math.sqrt(dims), dim=2)
        matched = target @ scores.transpose(1, 2)  # (B, 3, N): each source point's soft partner
        source_mean = source.mean(dim=2, keepdim=True)
        matched_mean = matched.mean(dim=2, keepdim=True)
        cross = (source - source_mean) @ (matched - matched_mean).transpose(1, 2)  # (B, 3, 3)
        rotations = []
        for h in cross:
            u, _, vh = torch.linalg.svd(h)
            v = vh.transpose(0, 1)
            rotation = v @ u.transpose(0, 1)
            if torch.det(rotation) < 0:
                rotation = v @ self.reflect @ u.transpose(0, 1)
            rotations.append(rotation)
        rotation = torch.stack(rotations)
        translation = matched_mean - rotation @ source_mean
        return rotation, translation[..., 0]


class DCPv1(nn.Module):
    """DGCNN embedding, identity pointer, SVD head: ``forward(source, target) -> (R, t)``."""

    def __init__(self, emb_dims: int = EMB_DIMS, k: int = K_NEIGHBOURS):
        super().__init__()
        self.emb_nn = DGCNNEmbedding(emb_dims, k)
        self.head = SVDHead()

    @torch.no_grad()
    def forward(self, source: torch.Tensor, target: torch.Tensor):
        """``source`` ``(B, 3, N)``, ``target`` ``(B, 3, M)`` -> ``R`` ``(B, 3, 3)``, ``t`` ``(B, 3)``,
        ``target ~= R source + t``."""
        source_embedding = self.emb_nn(source)
        target_embedding = self.emb_nn(target)
        # The identity pointer's output is added to the embedding: each one doubled.
        return self.head(source_embedding + source_embedding, target_embedding + target_embedding, source, target)
