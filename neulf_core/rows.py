"""Rows of a small learned per-view table, one per ray, with a gradient that repeats.

`table[view_index]` is exact, but its backward adds the rays' gradients into each view's row
(index_put_ with accumulate) from parallel threads on a CPU, in no fixed order: two runs of
the same seed then differ in rounding once the batch is large enough to be split (the tiny
test scene with pose refinement at 8192 rays a step, 2 threads), and a resumed run does not
repeat the run never stopped.  Here the backward adds them with index_add_, which a CPU does
in the index's order (a GPU's is not ordered either; there the indexing is left as it is).
"""

from __future__ import annotations

import torch


class _Rows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(index)
        ctx.rows = table.shape[0]
        return table[index]

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (index,) = ctx.saved_tensors
        flat = index.reshape(-1)
        per_row = grad.reshape(flat.numel(), *grad.shape[index.dim():])
        summed = grad.new_zeros((ctx.rows, *per_row.shape[1:])).index_add_(0, flat, per_row)
        return summed, None


def rows_of(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """`table[index]` for a (V, ...) table and a non-negative integer index of any shape."""
    if table.device.type != "cpu" or not table.requires_grad:
        return table[index]
    return _Rows.apply(table, index)
