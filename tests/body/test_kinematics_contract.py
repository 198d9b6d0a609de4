"""The pytorch-kinematics internals that torchfit relies on, pinned against its public API.

torchfit uses one private piece of pytorch-kinematics, in
``torchfit.body.kinematics._forward_kinematics``: ``Chain.forward_kinematics_tensor`` reads the
joint axes from ``chain.axes`` and the static frame offsets from ``chain._static_offsets``, which
that helper swaps for the body model's own buffers (zero-tangent dual tensors under forward-mode
AD, where pytorch-kinematics' public call with its plain constants costs ~3.5 ms more per call:
2-3x the forward kinematics of small batches). These tests fail, with a message saying what
changed, on a pytorch-kinematics upgrade that breaks this.
"""

from __future__ import annotations

from importlib.metadata import version

import pytest
import torch
import torch.autograd.forward_ad as fwad

from torchfit.body.kinematics import (
    TESTED_PK_VERSION,
    SkeletonChain,
    _forward_kinematics,
    chain_constants,
)
from torchfit.body.template import load_template

pk = pytest.importorskip("pytorch_kinematics")

UPGRADE = (
    "pytorch-kinematics {found} is installed; torchfit.body.kinematics._forward_kinematics "
    "swaps the private Chain attributes `axes` and `_static_offsets`, checked against "
    "pytorch-kinematics {tested} only. {what} Adapt _forward_kinematics (or use the public "
    "Chain.forward_kinematics_tensor with plain constants, slower under forward-mode AD), "
    "then update TESTED_PK_VERSION and the pin in pyproject.toml."
)


def fail(what: str) -> None:
    pytest.fail(
        UPGRADE.format(found=version("pytorch-kinematics"), tested=TESTED_PK_VERSION, what=what)
    )


@pytest.fixture(scope="module", params=["mpeg4_full", "mpeg4_simple"])
def template(request):
    return load_template(request.param)


@pytest.fixture(scope="module")
def skeleton(template) -> SkeletonChain:
    return SkeletonChain(template.urdf, template.segments, template.parents)


@pytest.fixture(scope="module")
def public_chain(template):
    """A fresh float64 chain of the same URDF, used through its public API only."""
    return pk.build_chain_from_urdf(template.urdf).to(dtype=torch.float64)


def joint_angles(skeleton, batch=5, seed=0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    lo, hi = skeleton.lower, skeleton.upper
    return lo + (hi - lo) * torch.rand(batch, skeleton.num_dofs, generator=g, dtype=torch.float64)


def test_installed_version_is_the_tested_one():
    found = version("pytorch-kinematics")
    if found != TESTED_PK_VERSION:
        fail(
            "Run tests/body/test_kinematics_contract.py against it: if everything else here "
            "passes, the internals are unchanged and TESTED_PK_VERSION can be bumped."
        )


def test_private_constants_exist_and_equal_the_public_values(template, skeleton):
    chain = pk.build_chain_from_urdf(template.urdf)
    axes, static = chain_constants(chain)  # public API: frames' joint/link offsets and axes
    n_frames = len(chain.get_frame_names(exclude_fixed=False))
    for attr, public, shape in (
        ("axes", axes, (len(chain.get_joint_parameter_names()), 3)),
        ("_static_offsets", static, (n_frames, 4, 4)),
    ):
        if not hasattr(chain, attr):
            fail(f"Chain has no attribute {attr!r} any more.")
        private = getattr(chain, attr)
        if not isinstance(private, torch.Tensor) or tuple(private.shape) != shape:
            fail(f"Chain.{attr} is no longer a {shape} tensor (got {private!r:.80}).")
        if private.dtype != chain.dtype or not torch.equal(private, public):
            fail(f"Chain.{attr} no longer holds the public values (see chain_constants).")
    # the model's buffers are those values in float64
    assert torch.equal(skeleton.axes, axes.double())
    assert torch.equal(skeleton.static_offsets, static.double())


def test_forward_kinematics_reads_the_swapped_constants(skeleton, public_chain):
    chain = skeleton.chain
    q = joint_angles(skeleton)
    before = chain.axes, chain._static_offsets
    # with the public values, the helper is the public call, bit for bit
    ours = _forward_kinematics(chain, q, skeleton.axes, skeleton.static_offsets)
    public = public_chain.forward_kinematics_tensor(q, analytical_grad=False)
    if ours.shape != public.shape or not torch.equal(ours, public):
        fail("forward_kinematics_tensor with the swapped constants differs from the public call.")
    # the swapped constants are what it uses: a translated root frame moves every frame
    shift = skeleton.static_offsets.clone()
    root = int(public_chain.get_frame_indices(public_chain.get_frame_names(exclude_fixed=False)[0]))
    shift[root, :3, 3] += torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    moved = _forward_kinematics(chain, q, skeleton.axes, shift)
    expected = public[..., :3, 3] + torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    if not torch.allclose(moved[..., :3, 3], expected, rtol=0, atol=1e-12):
        fail("forward_kinematics_tensor ignores Chain._static_offsets.")
    # reversed axes turn every joint the other way: the same as negated joint angles
    flipped = _forward_kinematics(chain, q, -skeleton.axes, skeleton.static_offsets)
    negated = public_chain.forward_kinematics_tensor(-q, analytical_grad=False)
    if not torch.allclose(flipped, negated, rtol=0, atol=1e-12):
        fail("forward_kinematics_tensor ignores Chain.axes.")
    # restored afterwards, also on an error
    assert chain.axes is before[0] and chain._static_offsets is before[1]
    with pytest.raises(Exception):  # noqa: B017 (whatever the chain raises)
        _forward_kinematics(chain, q, skeleton.axes[:, :2], skeleton.static_offsets)
    assert chain.axes is before[0] and chain._static_offsets is before[1]


def test_dual_constants_give_the_public_tangents(skeleton, public_chain):
    """Lifted (dual) constants: same primal and tangent as the public call with plain ones."""
    q = joint_angles(skeleton, seed=1)
    tangent = torch.randn(q.shape, generator=torch.Generator().manual_seed(2), dtype=q.dtype)
    with fwad.dual_level():
        dual = fwad.make_dual(q, tangent)
        ours = fwad.unpack_dual(skeleton._transforms(dual))
        ref = public_chain.forward_kinematics_tensor(dual, analytical_grad=False)
        ref = fwad.unpack_dual(ref[skeleton.frame_indices].transpose(0, 1))
    assert torch.equal(ours.primal, ref.primal)
    assert torch.equal(ours.tangent, ref.tangent)


def test_public_limits_and_names(skeleton, public_chain):
    """What the model takes from the public API: DOF order, limits, frame lookup."""
    assert skeleton.dof_names == public_chain.get_joint_parameter_names()
    lower, upper = public_chain.get_joint_limits()
    assert skeleton.lower.tolist() == lower and skeleton.upper.tolist() == upper
    for name in skeleton.dof_names:
        joint = public_chain.find_joint(name)
        assert joint.joint_type == "revolute"
        assert torch.equal(joint.axis.double(), skeleton.axes[skeleton.dof_names.index(name)])
