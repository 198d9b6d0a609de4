"""The NIST StRD nonlinear regression problems: parser, hand-coded models and batching helpers.

Shared by ``tests/solver/test_solver_nist.py`` and ``benchmarks/bench_solver.py``. The ``.dat``
files (27 problems, see ``shared/data/nist-strd/README.md``) hold a model equation as text only;
each model is coded here by hand from the header of its file. ``b`` is ``(N, P)`` (one parameter
row per problem copy) and the predictor ``x`` is ``(M,)`` (``(M, 2)`` for Nelson); every model
returns ``(N, M)`` predictions. Nelson's response is ``log(y)``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.autograd.forward_ad as fwad

__all__ = [
    "NistProblem",
    "MODELS",
    "load_problem",
    "load_all",
    "log_relative_error",
    "make_batch",
]

Tensor = torch.Tensor


def _misra1a(b: Tensor, x: Tensor) -> Tensor:
    return b[:, :1] * (1 - torch.exp(-b[:, 1:2] * x))


def _chwirut(b: Tensor, x: Tensor) -> Tensor:
    return torch.exp(-b[:, :1] * x) / (b[:, 1:2] + b[:, 2:3] * x)


def _lanczos(b: Tensor, x: Tensor) -> Tensor:
    return (
        b[:, :1] * torch.exp(-b[:, 1:2] * x)
        + b[:, 2:3] * torch.exp(-b[:, 3:4] * x)
        + b[:, 4:5] * torch.exp(-b[:, 5:6] * x)
    )


def _gauss(b: Tensor, x: Tensor) -> Tensor:
    return (
        b[:, :1] * torch.exp(-b[:, 1:2] * x)
        + b[:, 2:3] * torch.exp(-((x - b[:, 3:4]) ** 2) / b[:, 4:5] ** 2)
        + b[:, 5:6] * torch.exp(-((x - b[:, 6:7]) ** 2) / b[:, 7:8] ** 2)
    )


def _danwood(b: Tensor, x: Tensor) -> Tensor:
    return b[:, :1] * x ** b[:, 1:2]


def _misra1b(b: Tensor, x: Tensor) -> Tensor:
    return b[:, :1] * (1 - (1 + b[:, 1:2] * x / 2) ** (-2))


def _rational(num: int, den: int) -> Callable[[Tensor, Tensor], Tensor]:
    def model(b: Tensor, x: Tensor) -> Tensor:
        top = sum(b[:, k : k + 1] * x**k for k in range(num))
        bottom = 1 + sum(b[:, num + k - 1 : num + k] * x**k for k in range(1, den + 1))
        return top / bottom

    return model


def _nelson(b: Tensor, x: Tensor) -> Tensor:
    return b[:, :1] - b[:, 1:2] * x[:, 0] * torch.exp(-b[:, 2:3] * x[:, 1])


def _mgh17(b: Tensor, x: Tensor) -> Tensor:
    return b[:, :1] + b[:, 1:2] * torch.exp(-x * b[:, 3:4]) + b[:, 2:3] * torch.exp(-x * b[:, 4:5])


def _misra1c(b: Tensor, x: Tensor) -> Tensor:
    return b[:, :1] * (1 - (1 + 2 * b[:, 1:2] * x) ** (-0.5))


def _misra1d(b: Tensor, x: Tensor) -> Tensor:
    return b[:, :1] * b[:, 1:2] * x / (1 + b[:, 1:2] * x)


def _roszman1(b: Tensor, x: Tensor) -> Tensor:
    return b[:, :1] - b[:, 1:2] * x - torch.atan(b[:, 2:3] / (x - b[:, 3:4])) / math.pi


def _enso(b: Tensor, x: Tensor) -> Tensor:
    w = 2 * math.pi * x
    return (
        b[:, :1]
        + b[:, 1:2] * torch.cos(w / 12)
        + b[:, 2:3] * torch.sin(w / 12)
        + b[:, 4:5] * torch.cos(w / b[:, 3:4])
        + b[:, 5:6] * torch.sin(w / b[:, 3:4])
        + b[:, 7:8] * torch.cos(w / b[:, 6:7])
        + b[:, 8:9] * torch.sin(w / b[:, 6:7])
    )


def _mgh09(b: Tensor, x: Tensor) -> Tensor:
    return b[:, :1] * (x**2 + x * b[:, 1:2]) / (x**2 + x * b[:, 2:3] + b[:, 3:4])


def _rat42(b: Tensor, x: Tensor) -> Tensor:
    return b[:, :1] / (1 + torch.exp(b[:, 1:2] - b[:, 2:3] * x))


def _mgh10(b: Tensor, x: Tensor) -> Tensor:
    return b[:, :1] * torch.exp(b[:, 1:2] / (x + b[:, 2:3]))


def _eckerle4(b: Tensor, x: Tensor) -> Tensor:
    return (b[:, :1] / b[:, 1:2]) * torch.exp(-0.5 * ((x - b[:, 2:3]) / b[:, 1:2]) ** 2)


def _rat43(b: Tensor, x: Tensor) -> Tensor:
    return b[:, :1] / (1 + torch.exp(b[:, 1:2] - b[:, 2:3] * x)) ** (1 / b[:, 3:4])


def _bennett5(b: Tensor, x: Tensor) -> Tensor:
    return b[:, :1] * (b[:, 1:2] + x) ** (-1 / b[:, 2:3])


#: Model of each problem, coded from the equation in its file's header.
MODELS: dict[str, Callable[[Tensor, Tensor], Tensor]] = {
    "Misra1a": _misra1a,
    "Chwirut2": _chwirut,
    "Chwirut1": _chwirut,
    "Lanczos3": _lanczos,
    "Gauss1": _gauss,
    "Gauss2": _gauss,
    "DanWood": _danwood,
    "Misra1b": _misra1b,
    "Kirby2": _rational(3, 2),
    "Hahn1": _rational(4, 3),
    "Nelson": _nelson,
    "MGH17": _mgh17,
    "Lanczos1": _lanczos,
    "Lanczos2": _lanczos,
    "Gauss3": _gauss,
    "Misra1c": _misra1c,
    "Misra1d": _misra1d,
    "Roszman1": _roszman1,
    "ENSO": _enso,
    "MGH09": _mgh09,
    "Thurber": _rational(4, 3),
    "BoxBOD": _misra1a,
    "Rat42": _rat42,
    "MGH10": _mgh10,
    "Eckerle4": _eckerle4,
    "Rat43": _rat43,
    "Bennett5": _bennett5,
}


@dataclass
class NistProblem:
    """One NIST StRD problem.

    Attributes:
        name: dataset name, e.g. ``"Misra1a"``.
        difficulty: ``"lower"``, ``"average"`` or ``"higher"``.
        start1, start2, certified, certified_sd: ``(P,)`` float64.
        certified_rss: certified residual sum of squares.
        x: ``(M,)`` predictor (``(M, 2)`` for Nelson), float64.
        y: ``(M,)`` response (``log(y)`` for Nelson), float64.
    """

    name: str
    difficulty: str
    start1: Tensor
    start2: Tensor
    certified: Tensor
    certified_sd: Tensor
    certified_rss: float
    x: Tensor
    y: Tensor

    @property
    def n_params(self) -> int:
        return int(self.certified.numel())

    @property
    def n_obs(self) -> int:
        return int(self.y.numel())

    def model(self, b: Tensor) -> Tensor:
        """Predictions ``(N, M)`` for parameters ``b`` ``(N, P)``."""
        return MODELS[self.name](b, _lift(self.x.to(b.dtype), b))

    def residual(self, b: Tensor) -> Tensor:
        """Residuals ``y - model(b)``, ``(N, M)`` for ``b`` ``(N, P)``."""
        return _lift(self.y.to(b.dtype), b) - self.model(b)


def _lift(data: Tensor, like: Tensor) -> Tensor:
    """``data`` as a dual tensor with a zero tangent when ``like`` is a forward-AD dual tensor.

    Mixing a dual tensor with a plain one makes torch build an "efficient zero" tangent, whose
    arithmetic runs far slower on CPU (about 0.2–0.4 ms per operation in torch 2.13, measured)
    than with an explicit zero tangent. It changes no value.
    """
    if fwad.unpack_dual(like).tangent is None:
        return data
    return fwad.make_dual(data, torch.zeros_like(data))


def _line_range(header: list[str], label: str) -> tuple[int, int]:
    for line in header[:10]:
        m = re.search(label + r"\s*\(lines\s+(\d+)\s+to\s+(\d+)\)", line)
        if m:
            return int(m.group(1)), int(m.group(2))
    raise ValueError(f"no '{label} (lines a to b)' entry in the file header")


def load_problem(path: str | Path) -> NistProblem:
    """Parse one NIST StRD ``.dat`` file (line ranges read from its header)."""
    path = Path(path)
    lines = path.read_text().splitlines()
    name = path.stem
    if name not in MODELS:
        raise ValueError(f"{path}: no model coded for dataset {name!r}")
    start_lo, start_hi = _line_range(lines, "Starting Values")
    data_lo, data_hi = _line_range(lines, "Data")
    starts1, starts2, cert, sd = [], [], [], []
    for line in lines[start_lo - 1 : start_hi]:
        m = re.match(r"\s*b\d+\s*=\s*(\S+)\s+(\S+)\s+(\S+)\s+(\S+)", line)
        if not m:
            raise ValueError(f"{path}: cannot parse parameter line {line!r}")
        s1, s2, c, d = (float(v) for v in m.groups())
        starts1.append(s1)
        starts2.append(s2)
        cert.append(c)
        sd.append(d)
    rss = None
    difficulty = None
    for line in lines[: data_lo - 1]:
        if line.strip().startswith("Residual Sum of Squares:"):
            rss = float(line.split(":")[1])
        m = re.search(r"(Lower|Average|Higher) Level of Difficulty", line)
        if m:
            difficulty = m.group(1).lower()
    if rss is None or difficulty is None:
        raise ValueError(f"{path}: no certified RSS or difficulty level in the header")
    rows = [[float(v) for v in line.split()] for line in lines[data_lo - 1 : data_hi]]
    data = torch.tensor(rows, dtype=torch.float64)
    y, x = data[:, 0], data[:, 1:]
    if x.shape[1] == 1:
        x = x[:, 0]
    if name == "Nelson":
        y = torch.log(y)
    dt = torch.float64
    return NistProblem(
        name=name,
        difficulty=difficulty,
        start1=torch.tensor(starts1, dtype=dt),
        start2=torch.tensor(starts2, dtype=dt),
        certified=torch.tensor(cert, dtype=dt),
        certified_sd=torch.tensor(sd, dtype=dt),
        certified_rss=rss,
        x=x,
        y=y,
    )


def load_all(folder: str | Path) -> list[NistProblem]:
    """All 27 problems in the order of :data:`MODELS` (README table order)."""
    folder = Path(folder)
    return [load_problem(folder / f"{name}.dat") for name in MODELS]


def log_relative_error(estimate: Tensor, certified: Tensor, cap: float = 11.0) -> Tensor:
    """LRE = -log10(|estimate - certified| / |certified|), capped at ``cap`` digits.

    NaN estimates give 0. Shapes broadcast; returns float64.
    """
    est = estimate.to(torch.float64)
    cert = certified.to(torch.float64)
    rel = (est - cert).abs() / cert.abs()
    lre = -torch.log10(rel)
    lre = torch.nan_to_num(lre, nan=0.0, posinf=cap)
    return lre.clamp(0.0, cap)


def make_batch(
    problems: list[NistProblem], x0: list[Tensor]
) -> tuple[Callable[[Tensor], tuple[Tensor, Tensor]], Tensor]:
    """A padded, masked batch of (possibly different) problems for ``levenberg_marquardt``.

    Row ``b`` of the batch solves ``problems[b]`` from ``x0[b]``. Parameters are padded with
    zeros to the largest ``P`` (hold them fixed with ``lower == upper == 0``) and residuals with
    masked entries to the largest ``M``.

    Returns:
        ``(residual_fn, x0)``: ``residual_fn`` maps ``(K*B, P_max)`` (``K`` stacked copies of
        the batch, row ``i`` belongs to problem ``i % B``) to ``(r, mask)``, both
        ``(K*B, M_max)``; ``x0`` is ``(B, P_max)`` float64.
    """
    B = len(problems)
    p_max = max(p.n_params for p in problems)
    m_max = max(p.n_obs for p in problems)
    x0_pad = torch.zeros(B, p_max, dtype=torch.float64)
    for b, (prob, start) in enumerate(zip(problems, x0, strict=True)):
        x0_pad[b, : prob.n_params] = start
    names = sorted({p.name for p in problems}, key=list(MODELS).index)
    by_name = {n: next(p for p in problems if p.name == n) for n in names}
    rows_of = {n: [b for b in range(B) if problems[b].name == n] for n in names}

    def residual(x: Tensor) -> tuple[Tensor, Tensor]:
        k = x.shape[0] // B
        pieces, order, masks = [], [], []
        for n in names:
            prob = by_name[n]
            rows = torch.tensor([c * B + b for c in range(k) for b in rows_of[n]], dtype=torch.long)
            r = prob.residual(x.index_select(0, rows)[:, : prob.n_params])
            pieces.append(torch.nn.functional.pad(r, (0, m_max - prob.n_obs)))
            mask = torch.zeros(len(rows), m_max, dtype=torch.bool)
            mask[:, : prob.n_obs] = True
            masks.append(mask)
            order.append(rows)
        perm = torch.cat(order)
        inverse = torch.empty_like(perm)
        inverse[perm] = torch.arange(perm.numel())
        return torch.cat(pieces).index_select(0, inverse), torch.cat(masks)[inverse]

    return residual, x0_pad
