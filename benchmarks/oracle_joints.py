"""What the fit would gain from knowing where some joints are in one posture's image, or how
far they are from the camera.

A diagnostic, not a method: it reads ``truth.json``. Each subject's problem gets two more
least-squares residuals per named joint, ``weight * (fitted pixel - true pixel)``, the joint's
true world position (``joints_world.pose<j>``) projected with the subject's camera; with
``--depth`` one instead, ``weight * (fitted depth - true depth) / 1 cm``, the depth along the
camera's axis. Then the whole benchmark runs as ``tools/benchmark.py`` runs it:
segmentation, start, stages, judge, report. If the measurements come out right with the true
pixels (depths), the information missing from the fit is where those joints sit in that image
(how far from the camera); if they do not, it is elsewhere.

    python benchmarks/oracle_joints.py --data <dev set> --out DIR --joints l_knee,l_ankle \
        [--pose 3] [--weight 2] [--depth] [--config configs/benchmark.yaml] [--set KEY=VALUE ...]

``--weight 2``: one pixel (one centimetre) off costs as much as a posture whose contour is 2
pixels off on average. Only for development sets: it uses their truth.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import importlib.util
import sys
from pathlib import Path

import torch

from torchfit.camera import project_points, world_to_camera
from torchfit.fit.prior import PriorFit

REPO_ROOT = Path(__file__).resolve().parents[1]


class JointPixelFit(PriorFit):
    """A built problem (a :class:`PriorFit` or a subclass) with joint-pixel residuals appended
    after all its own.

    Made from a built problem by :func:`attach`, as a subclass of the problem's own class. The
    rows are the residual layout's last entries (counted as joint marks in a bend fit, as
    posture-prior entries otherwise; least squares, always valid) and dense in the solver's
    blocks.
    """

    def _attach(
        self, targets: torch.Tensor, joints: list[str], pose: int, weight: float, depth: bool
    ):
        self.targets = targets.to(**self.kw)  # (B, K, 2) pixels, or (B, K) depths
        self.joint_names, self.joint_pose, self.joint_weight = list(joints), pose, weight
        self.joint_depth = depth
        self.joint_segments = [self.model.template.joints[j] for j in joints]
        self.num_joint_rows = (1 if depth else 2) * len(joints)
        layout = self.residual_layout
        self.own_size = layout.size
        # the last entries of the layout: after a bend fit's own marks, else after e_A
        self.joint_block = "marks" if hasattr(self, "_mark_rows") else "pose_prior"
        count = f"num_{self.joint_block}"
        self.residual_layout = dataclasses.replace(
            layout, **{count: getattr(layout, count) + self.num_joint_rows}
        )

    def subset(self, index: list[int]) -> JointPixelFit:
        out = super().subset(index)
        out.__class__ = type(self)
        out._attach(
            self.targets[index],
            self.joint_names,
            self.joint_pose,
            self.joint_weight,
            self.joint_depth,
        )
        return out

    def joint_residual(self, full: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """(N, 2K) ``weight * (fitted - true pixel)`` of the joints, or (N, K) ``weight *
        (fitted - true depth) / 1 cm``."""
        one = torch.zeros(1, dtype=torch.long, device=full.device)  # pose no vertex but one
        _, origins = self.pose_world(full, self.joint_pose, rows, one)
        if self.joint_depth:
            depth = world_to_camera(origins[:, self.joint_segments], self.camera[rows])[..., 2]
            return self.joint_weight * 100.0 * (depth - self.targets[rows])
        pixels = project_points(origins[:, self.joint_segments], self.camera[rows])
        return (self.joint_weight * (pixels - self.targets[rows])).reshape(full.shape[0], -1)

    def residual(self, full, selections=None, rows=None) -> torch.Tensor:
        if rows is None:
            rows = torch.arange(full.shape[0], device=full.device)
        own = super().residual(full, selections, rows)
        return torch.cat([own, self.joint_residual(full, rows)], 1)

    def jacobian_blocks(self, free: torch.Tensor) -> list[tuple[slice, torch.Tensor]]:
        out = []
        held = getattr(self.residual_layout, self.joint_block)
        for rows, cols in super().jacobian_blocks(free):
            if rows == held:  # the problem's own last rows; the joint rows stay dense
                rows = slice(held.start, held.stop - self.num_joint_rows)
            if rows.stop > rows.start:
                out.append((rows, cols))
        return out

    def jacobian_and_residual(self, full, free, selections, rows=None):
        if rows is None:
            rows = torch.arange(full.shape[0], device=full.device)
        jac, r = super().jacobian_and_residual(full, free, selections, rows)
        x = full.detach().clone().requires_grad_(True)
        with torch.enable_grad():
            extra = self.joint_residual(x, rows)
            for k in range(extra.shape[1]):  # row n depends on x[n] alone
                grad = torch.autograd.grad(extra[:, k].sum(), x, retain_graph=True)[0]
                jac[:, self.own_size + k] = grad[:, free]
        return jac, torch.cat([r[:, : self.own_size], extra.detach()], 1)


def with_joint_rows(
    fit: PriorFit,
    targets: torch.Tensor,
    joints: list[str],
    pose: int,
    weight: float,
    depth: bool = False,
) -> JointPixelFit:
    """Turn a built problem (a :class:`PriorFit` or a subclass, e.g. a bend fit) into a
    :class:`JointPixelFit` of its own class, with the joints' target pixels (B, K, 2) or, with
    ``depth``, their target depths along the camera axis (B, K)."""
    fit.__class__ = type(f"JointPixel{type(fit).__name__}", (JointPixelFit, type(fit)), {})
    fit._attach(targets, joints, pose, weight, depth)
    return fit


def attach(
    fit: PriorFit, subjects, joints: list[str], pose: int, weight: float, depth: bool = False
) -> JointPixelFit:
    """Turn a built problem into a :class:`JointPixelFit` for ``subjects`` (their truth)."""
    targets = []
    for s in subjects:
        world = torch.tensor(
            [[s.truth["joints_world"][f"pose{pose}"][j] for j in joints]], dtype=torch.float64
        )
        camera = s.camera.to(dtype=torch.float64)
        if depth:
            targets.append(world_to_camera(world, camera)[0, :, 2])
        else:
            targets.append(project_points(world, camera)[0])
    return with_joint_rows(fit, torch.stack(targets), joints, pose, weight, depth)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--joints", default="l_knee", help="comma-separated design.md joint names")
    p.add_argument("--pose", type=int, default=3)
    p.add_argument("--weight", type=float, default=2.0)
    p.add_argument("--depth", action="store_true", help="pin the joints' depths, not pixels")
    p.add_argument("--config", default=str(REPO_ROOT / "configs" / "benchmark.yaml"))
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args()
    joints = args.joints.split(",")
    run_module = importlib.import_module("torchfit.pipeline.run")
    fit_batch_problem, build = run_module._fit, run_module.build_problem
    current: dict = {}

    def fit_with_subjects(prepared, *a, **kw):
        current["subjects"] = [q.subject for q in prepared]
        return fit_batch_problem(prepared, *a, **kw)

    def build_with_joints(model, person, config, facts):
        fit = build(model, person, config, facts)
        if not isinstance(fit, PriorFit):  # no prior weighed: a PriorFit without one
            fit = PriorFit(fit.model, fit.person, fit.options, fit.scale_bounds)
        return attach(fit, current["subjects"], joints, args.pose, args.weight, args.depth)

    run_module._fit, run_module.build_problem = fit_with_subjects, build_with_joints
    spec = importlib.util.spec_from_file_location("benchmark", REPO_ROOT / "tools" / "benchmark.py")
    benchmark = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(benchmark)
    argv = ["--config", args.config, "--data", args.data, "--out", args.out]
    for item in ["output.tensorboard=false", "output.overlays=false", *args.set]:
        argv += ["--set", item]
    sys.exit(benchmark.main(argv))


if __name__ == "__main__":
    main()
