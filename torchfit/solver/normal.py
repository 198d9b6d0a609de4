"""Per-problem reductions of the Levenberg–Marquardt solver: the cost and the normal equations.

Every sum over a problem's residual entries is formed here, from that problem's own valid
entries copied into a fresh buffer, so it runs on the same numbers in the same shapes whether
the problem is solved alone or in any position of any batch. Batched matrix products do not
give that: a ``(B, P, M) @ (B, M, P)`` product rounds a row differently for different ``B``
or row positions (MKL's batched kernels), and padding entries, although zero, change how the
remaining ones are grouped in a sum. One product per problem costs a Python loop over the
running problems, which is small beside a residual evaluation.

The damped systems are factored and solved the same way (:func:`cholesky_each`,
:func:`cholesky_solve_each`): on the CPU, MKL's kernels round by the memory alignment of
their data, which a matrix's place in a batch changes, so each problem's system is factored
and solved on a fresh copy, as it is alone.

A per-residual weighting (a robust loss) belongs in :func:`normal_equations` and
:func:`half_squared_norm`: they are the only places where residuals and the Jacobian are
reduced.
"""

from __future__ import annotations

import torch

__all__ = [
    "valid_entries",
    "half_squared_norm",
    "half_sum",
    "Block",
    "normal_equations",
    "jacobian_times",
    "jacobian_t_times",
    "cholesky_each",
    "cholesky_solve_each",
]


def valid_entries(mask: torch.Tensor | None, batch: int) -> list[torch.Tensor | None]:
    """Per problem, the ``(m_b,)`` indices of its valid residual entries (None: all of them).

    Args:
        mask: ``(B, M)`` bool, or None when every entry is valid.
        batch: ``B``.
    """
    if mask is None:
        return [None] * batch
    # one nonzero over the batch, split by rows: the same ascending indices per row as each
    # row's own nonzero, with two host synchronisations instead of one per problem
    columns = mask.nonzero()[:, 1].contiguous()
    return list(columns.split(mask.sum(1).tolist()))


def _own(values: torch.Tensor, index: torch.Tensor | None, dim: int) -> torch.Tensor:
    """A fresh contiguous copy of one problem's valid entries along ``dim``."""
    if index is None:
        return values.clone(memory_format=torch.contiguous_format)
    return values.index_select(dim, index)


def half_squared_norm(r: torch.Tensor, valid: list[torch.Tensor | None]) -> torch.Tensor:
    """``(B,)`` cost ``0.5 * |r_b|²`` over each problem's valid entries.

    Args:
        r: ``(B, M)`` residuals.
        valid: from :func:`valid_entries`.
    """
    out = torch.empty(r.shape[0], dtype=r.dtype, device=r.device)
    for b in range(r.shape[0]):
        own = _own(r[b], valid[b], 0)
        out[b] = 0.5 * torch.dot(own, own)
    return out


def half_sum(values: torch.Tensor, valid: list[torch.Tensor | None]) -> torch.Tensor:
    """``(B,)`` ``0.5 * sum(values_b)`` over each problem's valid entries (a robust cost).

    Args:
        values: ``(B, M)`` per-entry costs.
        valid: from :func:`valid_entries`.
    """
    out = torch.empty(values.shape[0], dtype=values.dtype, device=values.device)
    for b in range(values.shape[0]):
        out[b] = 0.5 * _own(values[b], valid[b], 0).sum()
    return out


#: A block of a Jacobian's sparsity: a range of residual entries (rows) and the parameters
#: (columns, a (c,) int64 tensor) they depend on; every other column of those rows is zero.
Block = tuple[slice, torch.Tensor]


def normal_equations(
    jac: torch.Tensor,
    r: torch.Tensor,
    valid: list[torch.Tensor | None],
    blocks: list[Block] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``A = JᵀJ`` ``(B, P, P)`` and ``g = Jᵀr`` ``(B, P)``, one product per problem.

    Args:
        jac: ``(B, M, P)`` Jacobian (the built-in ones are views of ``(B, P, M)`` storage,
            whose per-problem copies are then plain row gathers).
        r: ``(B, M)`` residuals.
        valid: from :func:`valid_entries`.
        blocks: optional sparsity of ``J`` (:data:`Block`, disjoint row ranges): each block
            adds ``J_kᵀ J_k`` over its own columns only, ``c_k²`` instead of ``P²``
            multiply-adds per row; rows outside every block count as one block over all
            columns. The blocks are summed in their order, then those rows, for every problem
            alike.
    """
    b_size, m, p = jac.shape
    a_mat = torch.empty(b_size, p, p, dtype=jac.dtype, device=jac.device)
    grad = torch.empty(b_size, p, dtype=jac.dtype, device=jac.device)
    if blocks is not None:
        parts = _with_rest(blocks, m, p, jac.device)
        for b in range(b_size):
            a_mat[b], grad[b] = _block_products(jac[b], r[b], valid[b], parts)
        return a_mat, grad
    jac_t = jac.transpose(1, 2)
    for b in range(b_size):
        index = valid[b]
        jt = _own(jac_t[b], index, 1)  # (P, m_b)
        a_mat[b] = jt @ jt.T
        grad[b] = jt @ _own(r[b], index, 0)
    return a_mat, grad


def _with_rest(blocks: list[Block], m: int, p: int, device: torch.device) -> list:
    """The blocks as (row indices, columns), then the rows outside them over every column."""
    covered = torch.zeros(m, dtype=torch.bool, device=device)
    parts = []
    for rows, cols in blocks:
        if bool(covered[rows].any()):
            raise ValueError(f"Jacobian blocks overlap in rows {rows}")
        covered[rows] = True
        parts.append((torch.arange(m, device=device)[rows], cols.to(device)))
    rest = (~covered).nonzero()[:, 0]
    if rest.numel():
        parts.append((rest, torch.arange(p, device=device)))
    return parts


def _block_products(
    jac: torch.Tensor, r: torch.Tensor, index: torch.Tensor | None, parts: list
) -> tuple[torch.Tensor, torch.Tensor]:
    """One problem's ``JᵀJ`` (P, P) and ``Jᵀr`` (P,) summed block by block over its valid
    entries."""
    p = jac.shape[1]
    a_mat = torch.zeros(p, p, dtype=jac.dtype, device=jac.device)
    grad = torch.zeros(p, dtype=jac.dtype, device=jac.device)
    for rows, cols in parts:
        own = rows if index is None else _intersect(index, rows)
        if not own.numel() or not cols.numel():
            continue
        jb = jac.index_select(0, own).index_select(1, cols)  # (m_k, c_k), a fresh copy
        a_mat[cols[:, None], cols] += jb.T @ jb
        grad[cols] += jb.T @ r.index_select(0, own)
    return a_mat, grad


def _intersect(index: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """The entries of the sorted ``index`` that are in ``rows`` (sorted)."""
    if rows.numel() and bool((rows[1:] - rows[:-1] == 1).all()):  # a range
        lo, hi = torch.searchsorted(index, rows[[0, -1]] + torch.tensor([0, 1], device=rows.device))
        return index[int(lo) : int(hi)]
    return index[torch.isin(index, rows)]


def jacobian_times(
    jac: torch.Tensor, v: torch.Tensor, valid: list[torch.Tensor | None]
) -> torch.Tensor:
    """``(B, M)`` products ``J_b v_b`` (zero on invalid entries), one per problem."""
    out = torch.zeros(jac.shape[:2], dtype=jac.dtype, device=jac.device)
    jac_t = jac.transpose(1, 2)
    for b in range(jac.shape[0]):
        index = valid[b]
        jt = _own(jac_t[b], index, 1)
        prod = jt.T @ v[b].clone()
        if index is None:
            out[b] = prod
        else:
            out[b, index] = prod
    return out


def jacobian_t_times(
    jac: torch.Tensor, v: torch.Tensor, valid: list[torch.Tensor | None]
) -> torch.Tensor:
    """``(B, P)`` products ``J_bᵀ v_b`` over each problem's valid entries, one per problem."""
    out = torch.empty(jac.shape[0], jac.shape[2], dtype=jac.dtype, device=jac.device)
    jac_t = jac.transpose(1, 2)
    for b in range(jac.shape[0]):
        index = valid[b]
        out[b] = _own(jac_t[b], index, 1) @ _own(v[b], index, 0)
    return out


def cholesky_each(matrices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``torch.linalg.cholesky_ex`` of ``(B, P, P)`` symmetric matrices, each problem's factor
    the one it has alone: on the CPU one factorisation per problem, on a fresh copy (MKL
    rounds by the data's alignment, which a matrix's offset in the batch changes); on other
    devices one batched call.

    Returns:
        ``(L, info)``, ``(B, P, P)`` and ``(B,)`` as ``cholesky_ex`` gives them.
    """
    if matrices.device.type != "cpu":
        return torch.linalg.cholesky_ex(matrices)
    factor = torch.empty_like(matrices)
    info = torch.empty(matrices.shape[0], dtype=torch.int32)
    for b in range(matrices.shape[0]):
        factor[b], info[b] = torch.linalg.cholesky_ex(matrices[b].clone())
    return factor, info


def cholesky_solve_each(rhs: torch.Tensor, factor: torch.Tensor) -> torch.Tensor:
    """``(B, P)`` solutions of ``L Lᵀ h = rhs`` for the ``(B, P, P)`` factors of
    :func:`cholesky_each`, per problem on fresh copies on the CPU (as there)."""
    if rhs.device.type != "cpu":
        return torch.cholesky_solve(rhs[:, :, None], factor)[:, :, 0]
    out = torch.empty_like(rhs)
    for b in range(rhs.shape[0]):
        out[b] = torch.cholesky_solve(rhs[b, :, None].clone(), factor[b].clone())[:, 0]
    return out
