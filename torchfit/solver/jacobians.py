"""Residual evaluation and batched Jacobians ``(B, M, P)`` for the Levenberg–Marquardt solver.

A residual function maps ``(N, P)`` to ``(N, M)`` residuals, or to a pair ``(r, mask)`` where
``mask`` is a ``(N, M)`` bool tensor of valid entries (``False`` marks padding of ragged data;
those entries count as zero in the cost and the Jacobian, whatever value ``r`` holds there).
Rows must be independent problems: row ``i`` of the output may depend on row ``i`` of the input
only. ``N`` is ``B`` for plain evaluations and ``K * B`` for folded Jacobian evaluations, which
stack ``K`` copies of the batch along dimension 0 (row ``i`` belongs to problem ``i % B``); a
residual function that holds per-problem data of ``B`` rows should tile it ``N // B`` times.

None of the Jacobians uses ``torch.func.vmap``, so residual functions that write in place (for
example pytorch-kinematics) work: forward mode uses ``torch.autograd.forward_ad`` dual tensors
with the ``P`` tangent directions folded into the batch (unless the batch alone is large);
reverse mode runs ``M`` vector-Jacobian products (one backward pass each, or a single one on
``M`` folded copies). No block-diagonal ``(B*M, B*P)`` matrix is ever built. The forward-mode
and finite-difference Jacobians come back as ``(B, M, P)`` views of ``(B, P, M)``-contiguous
storage, the layout in which the solver's ``JᵀJ`` and ``Jᵀr`` are fastest.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.autograd.forward_ad as fwad

from torchfit.solver.options import SolverError

__all__ = [
    "ResidualFn",
    "JacobianFn",
    "evaluate_residual",
    "jacobian_forward",
    "jacobian_reverse",
    "jacobian_numeric",
    "make_jacobian",
    "rows_caller",
]

ResidualOut = torch.Tensor | tuple[torch.Tensor, torch.Tensor]
ResidualFn = Callable[[torch.Tensor], ResidualOut]
#: A user Jacobian: ``x (B, P) -> J (B, M, P)``.
JacobianFn = Callable[[torch.Tensor], torch.Tensor]

# Forward mode folds the P tangent copies into one call unless one copy of the batch alone holds
# at least this many residuals (B * M); then it makes one call per tangent. Each dual-tensor
# operation makes several temporaries of its output's size, and once they no longer fit in a
# core's L2 cache the time per element grows up to threefold; a call that large is dominated by
# that array work, so more calls cost little. Below it, folding wins: the residual function's
# per-call overhead (Python, small operations) is paid once. Measured with torch 2.13 on a
# shared 2-core Xeon (2 MiB of L2 per core), minimum of 15 calls: NIST Chwirut2 (P = 3,
# M = 54) at B = 1024, 7.7-9.7 ms folded against 6.8-7.4 ms in three calls; the padded batch of
# all 27 NIST problems from both starts (B = 54, P = 9, M = 250), 31 ms folded against 86 ms in
# five calls. The Jacobian does not depend on the grouping: rows are independent.
FORWARD_UNFOLD_MIN_RESIDUALS = 1 << 15

_FOLD_HINT = (
    " (folded evaluations pass K stacked copies of the batch, shape (K*B, P), row i belonging"
    " to problem i % B: tile per-problem data x.shape[0] // B times, or set"
    " LMOptions(fold_batch=False))"
)


def evaluate_residual(
    fn: ResidualFn, x: torch.Tensor, m: int | None = None
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Call ``fn(x)`` and check what it returns.

    Args:
        fn: the residual function.
        x: ``(N, P)`` parameters.
        m: the expected number of residuals ``M`` (None on the first call).

    Returns:
        ``(r, mask)``: ``r`` ``(N, M)`` with masked entries set to zero, ``mask`` ``(N, M)``
        bool or None.

    Raises:
        SolverError: when ``fn`` returns something other than a tensor ``(N, M)`` or a pair
            ``(r, mask)`` with ``mask`` a bool tensor of the same shape.
    """
    out = fn(x)
    mask = None
    if isinstance(out, tuple):
        if len(out) != 2:
            raise SolverError(
                f"residual_fn: expected a tensor or a pair (r, mask), got a tuple of {len(out)}"
            )
        out, mask = out
    if not isinstance(out, torch.Tensor):
        raise SolverError(f"residual_fn: expected a torch.Tensor, got {type(out).__name__}")
    n = x.shape[0]
    if out.dim() != 2 or out.shape[0] != n or (m is not None and out.shape[1] != m):
        expected = f"({n}, {m if m is not None else 'M'})"
        raise SolverError(
            f"residual_fn: expected residuals of shape {expected} for x of shape "
            f"{tuple(x.shape)}, got {tuple(out.shape)}"
        )
    if mask is not None:
        if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
            raise SolverError(
                f"residual_fn: the mask must be a bool tensor, got "
                f"{getattr(mask, 'dtype', type(mask).__name__)}"
            )
        if mask.shape != out.shape:
            raise SolverError(
                f"residual_fn: mask shape {tuple(mask.shape)} differs from residual shape "
                f"{tuple(out.shape)}"
            )
        out = torch.where(mask, out, torch.zeros((), dtype=out.dtype, device=out.device))
    return out, mask


def _apply_mask(jac: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    if mask is None:
        return jac
    zero = torch.zeros((), dtype=jac.dtype, device=jac.device)
    # Masked in the (B, P, M) layout, which the built-in Jacobians are stored in.
    return torch.where(mask[:, None, :], jac.transpose(1, 2), zero).transpose(1, 2)


def _as_bmp(jac_t: torch.Tensor) -> torch.Tensor:
    """``(B, M, P)`` view of a ``(B, P, M)`` Jacobian, stored ``(B, P, M)``-contiguous.

    That storage makes ``JᵀJ`` and ``Jᵀr`` plain batched products of contiguous matrices,
    about twice as fast as on a ``(B, M, P)``-contiguous tensor.
    """
    return jac_t.detach().contiguous().transpose(1, 2)


def _call_folded(fn: ResidualFn, x_rep: torch.Tensor, m: int, batch: int) -> torch.Tensor:
    try:
        out, _ = evaluate_residual(fn, x_rep, m)
    except SolverError as exc:
        raise SolverError(f"{exc}{_FOLD_HINT}") from exc
    except RuntimeError as exc:
        raise SolverError(
            f"residual_fn failed on a folded batch of {x_rep.shape[0]} rows (B = {batch}): "
            f"{exc}{_FOLD_HINT}"
        ) from exc
    return out


def jacobian_forward(
    fn: ResidualFn, x: torch.Tensor, m: int, mask: torch.Tensor | None, fold: bool = True
) -> torch.Tensor:
    """Forward-mode Jacobian with dual tensors, ``(B, M, P)``.

    With ``fold`` the residual function runs once on ``(P*B, P)`` dual inputs whose block ``k``
    carries the tangent ``e_k``, or, when ``B * M`` reaches
    :data:`FORWARD_UNFOLD_MIN_RESIDUALS`, ``P`` times on ``(B, P)`` (cache-sized calls);
    without ``fold`` it runs ``P`` times on ``(B, P)``.
    """
    b, p = x.shape
    eye = torch.eye(p, dtype=x.dtype, device=x.device)
    with fwad.dual_level():
        if fold:
            per_call = 1 if b * m >= FORWARD_UNFOLD_MIN_RESIDUALS else p
            jac_t = torch.empty(b, p, m, dtype=x.dtype, device=x.device)
            for k0 in range(0, p, per_call):
                k = min(per_call, p - k0)
                x_rep = x.repeat(k, 1)
                tangent = eye[k0 : k0 + k].repeat_interleave(b, dim=0)
                out = _call_folded(fn, fwad.make_dual(x_rep, tangent), m, b)
                tan = fwad.unpack_dual(out).tangent
                if tan is None:
                    jac_t[:, k0 : k0 + k] = 0
                else:
                    jac_t[:, k0 : k0 + k] = tan.detach().reshape(k, b, m).transpose(0, 1)
        else:
            cols = []
            for k in range(p):
                out, _ = evaluate_residual(fn, fwad.make_dual(x, eye[k].expand(b, p)), m)
                tan = fwad.unpack_dual(out).tangent
                cols.append(torch.zeros_like(out) if tan is None else tan)
            jac_t = torch.stack(cols, dim=1)
    return _apply_mask(_as_bmp(jac_t), mask)


def jacobian_reverse(
    fn: ResidualFn, x: torch.Tensor, m: int, mask: torch.Tensor | None, fold: bool = True
) -> torch.Tensor:
    """Reverse-mode Jacobian from ``M`` vector-Jacobian products, ``(B, M, P)``.

    Rows are independent, so the gradient of ``sum_b r[b, j]`` gives row ``j`` of every
    problem's Jacobian. With ``fold`` one backward pass runs on ``M`` stacked copies of the
    batch; otherwise ``M`` backward passes reuse one graph.
    """
    b, p = x.shape
    with torch.enable_grad():
        if fold:
            x_rep = x.detach().repeat(m, 1).requires_grad_(True)
            out = _call_folded(fn, x_rep, m, b).reshape(m, b, m)
            picked = torch.diagonal(out, dim1=0, dim2=2)  # (B, M): copy j, residual j
            if not picked.requires_grad:
                return torch.zeros(b, m, p, dtype=x.dtype, device=x.device)
            (grad,) = torch.autograd.grad(picked.sum(), x_rep, allow_unused=True)
            if grad is None:
                grad = torch.zeros_like(x_rep)
            jac = grad.reshape(m, b, p).permute(1, 0, 2)
        else:
            x_req = x.detach().requires_grad_(True)
            out, _ = evaluate_residual(fn, x_req, m)
            if not out.requires_grad:
                return torch.zeros(b, m, p, dtype=x.dtype, device=x.device)
            rows = []
            for j in range(m):
                (grad,) = torch.autograd.grad(
                    out[:, j].sum(), x_req, retain_graph=j < m - 1, allow_unused=True
                )
                rows.append(torch.zeros_like(x) if grad is None else grad)
            jac = torch.stack(rows, dim=1)
    return _apply_mask(jac.detach().contiguous(), mask)


def jacobian_numeric(
    fn: ResidualFn,
    x: torch.Tensor,
    r: torch.Tensor,
    mask: torch.Tensor | None,
    upper: torch.Tensor | None = None,
    fold: bool = True,
) -> torch.Tensor:
    """Forward-difference Jacobian, ``(B, M, P)``.

    Step ``h_k = sqrt(eps) * max(1, |x_k|)`` (eps of ``x.dtype``), taken backwards where
    ``x_k + h_k`` would pass ``upper``. ``r`` ``(B, M)`` is the residual at ``x``.
    """
    b, p = x.shape
    m = r.shape[1]
    h = torch.finfo(x.dtype).eps ** 0.5 * x.abs().clamp_min(1.0)
    if upper is not None:
        h = torch.where(x + h > upper, -h, h)
    eye = torch.eye(p, dtype=x.dtype, device=x.device)
    if fold:
        x_rep = (x[None] + h[None] * eye[:, None, :]).reshape(p * b, p)
        out = _call_folded(fn, x_rep, m, b).reshape(p, b, m)
    else:
        out = torch.stack([evaluate_residual(fn, x + h * eye[k], m)[0] for k in range(p)])
    # Difference against the exact step taken (x + h) - x, which differs from h by rounding.
    step = ((x + h) - x).T[:, :, None]  # (P, B, 1)
    return _apply_mask(_as_bmp(((out - r[None]) / step).transpose(0, 1)), mask)


def make_jacobian(
    jacobian: str | JacobianFn,
    fn: ResidualFn,
    p: int,
    m: int,
    upper: torch.Tensor | None,
    fold: bool,
) -> Callable[[torch.Tensor, torch.Tensor, torch.Tensor | None], torch.Tensor]:
    """The Jacobian routine ``(x, r, mask) -> J (B, M, P)`` for a ``jacobian`` argument.

    ``"autograd"`` picks forward mode when ``P <= M`` and reverse mode otherwise; ``"forward"``,
    ``"reverse"`` and ``"numeric"`` force one; a callable ``x (B, P) -> (B, M, P)`` is used as
    given (masked entries are zeroed). A callable may also return ``(J, r)``: the Jacobian and
    a *refreshed* residual at ``x``, for problems whose residual is redefined between steps
    (data association, e.g. contour correspondences); the solver then takes ``r`` and its
    cost as the values at ``x`` for the problems it updates.

    Raises:
        SolverError: for an unknown ``jacobian`` string, or (when called) a callable that
            returns the wrong shape.
    """
    if callable(jacobian):
        user = jacobian

        def call_user(x: torch.Tensor, r: torch.Tensor, mask: torch.Tensor | None):
            out = user(x)
            refreshed = None
            if isinstance(out, tuple):
                if len(out) != 2:
                    raise SolverError(
                        f"jacobian: expected J or a pair (J, r), got a tuple of {len(out)}"
                    )
                out, refreshed = out
                if not isinstance(refreshed, torch.Tensor) or refreshed.shape != r.shape:
                    got = getattr(refreshed, "shape", type(refreshed).__name__)
                    raise SolverError(
                        f"jacobian: the refreshed residual must have shape {tuple(r.shape)}, "
                        f"got {tuple(got) if isinstance(got, torch.Size) else got}"
                    )
                refreshed = _apply_mask(refreshed.detach().to(x.dtype)[:, :, None], mask)[..., 0]
            jac = out
            if not isinstance(jac, torch.Tensor) or tuple(jac.shape) != (x.shape[0], m, p):
                got = tuple(jac.shape) if isinstance(jac, torch.Tensor) else type(jac).__name__
                raise SolverError(f"jacobian: expected shape ({x.shape[0]}, {m}, {p}), got {got}")
            jac = _apply_mask(jac.detach().to(x.dtype), mask)
            return jac if refreshed is None else (jac, refreshed)

        return call_user
    if jacobian == "autograd":
        jacobian = "forward" if p <= m else "reverse"
    if jacobian == "forward":
        return lambda x, r, mask: jacobian_forward(fn, x, m, mask, fold)
    if jacobian == "reverse":
        return lambda x, r, mask: jacobian_reverse(fn, x, m, mask, fold)
    if jacobian == "numeric":
        return lambda x, r, mask: jacobian_numeric(fn, x, r, mask, upper, fold)
    raise SolverError(
        "jacobian: expected 'autograd', 'forward', 'reverse', 'numeric' or a callable, "
        f"got {jacobian!r}"
    )


def rows_caller(fn: Callable, indexed: bool, problems: torch.Tensor, x_all: torch.Tensor):
    """``fn`` as a function of the rows of ``problems`` (``(N,)`` problem indices).

    An indexed ``fn`` gets ``(x, index)``, ``index`` the problem of each row (``K`` stacked
    copies repeat ``problems``). A plain one gets the whole batch, ``x_all`` with the rows of
    ``problems`` replaced by ``x`` (differentiably), and its rows of ``problems`` are kept.
    """
    n, bsz = problems.numel(), x_all.shape[0]
    if indexed:
        return lambda x: fn(x, problems.repeat(x.shape[0] // n))
    if n == bsz and bool((problems == torch.arange(bsz, device=problems.device)).all()):
        return fn

    def call(x: torch.Tensor):
        k = x.shape[0] // n
        rows = (torch.arange(k, device=x.device)[:, None] * bsz + problems[None]).flatten()
        source = torch.arange(k * bsz, device=x.device) + k * n  # rows of x_all.repeat(k, 1)
        source[rows] = torch.arange(k * n, device=x.device)  # rows of x
        out = fn(torch.cat([x, x_all.repeat(k, 1).to(x.dtype)])[source])
        if isinstance(out, tuple):
            return tuple(o[rows] if isinstance(o, torch.Tensor) else o for o in out)
        return out[rows] if isinstance(out, torch.Tensor) else out

    return call
