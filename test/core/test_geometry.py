"""sym3_eigh: batched Jacobi eigen-decomposition of symmetric 3x3 matrices against LAPACK."""

import pytest
import torch

from soma_ros.core.geometry import covariance_from_scale_rot, quat_normalize, quat_to_rotmat, sym3_eigh


def _covs(n=2000, seed=0):
    g = torch.Generator().manual_seed(seed)
    q = quat_normalize(torch.randn(n, 4, generator=g, dtype=torch.float64))
    s = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.01 + 1e-4
    s[: n // 4] = s[: n // 4, :1]                        # isotropic: all three eigenvalues equal
    s[n // 4: n // 2, 1] = s[n // 4: n // 2, 0]          # two equal
    s[n // 2: n // 2 + 10] = torch.tensor([1e-3, 1e-9, 1e-9], dtype=torch.float64)  # needles
    F = torch.eye(3, dtype=torch.float64) + 0.1 * torch.randn(n, 3, 3, generator=g, dtype=torch.float64)
    C = covariance_from_scale_rot(s, q)
    C[n // 2 + 10:] = F[n // 2 + 10:] @ C[n // 2 + 10:] @ F[n // 2 + 10:].transpose(-1, -2)  # stretched
    return C, quat_to_rotmat(q)


@pytest.mark.parametrize("use_init", [False, True])
def test_sym3_eigh_reconstructs_and_matches_lapack(use_init):
    C, R = _covs()
    evals, V = sym3_eigh(C, init=R if use_init else None)
    recon = V @ torch.diag_embed(evals) @ V.transpose(-1, -2)
    rel = (recon - C).flatten(1).norm(dim=-1) / C.flatten(1).norm(dim=-1)
    assert float(rel.max()) < 1e-12
    eye = torch.eye(3, dtype=C.dtype)
    assert float((V.transpose(-1, -2) @ V - eye).abs().max()) < 1e-12
    assert torch.allclose(torch.linalg.det(V), torch.ones(len(C), dtype=C.dtype), atol=1e-12)  # rotations
    ref = torch.linalg.eigvalsh(C)
    assert torch.allclose(evals.sort(dim=-1).values, ref, rtol=1e-10, atol=1e-18)


def test_sym3_eigh_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"\[N, 3, 3\]"):
        sym3_eigh(torch.zeros(4, 2, 2))
    with pytest.raises(ValueError, match="init"):
        sym3_eigh(torch.eye(3).expand(4, 3, 3), init=torch.eye(3))


def test_to_splats_gives_back_the_covariances():
    """The splat cloud's quaternions and scales rebuild the state's covariances."""
    from soma_ros.core.config import load_model_config
    from soma_ros.core.scenes import synthetic_bundle
    from soma_ros.core.simulator import Simulator

    torch.manual_seed(0)
    bundle = synthetic_bundle(600, seed=0, width=64, height=48)
    sim = Simulator(load_model_config("cpu", object="rope"))
    with torch.no_grad():
        st = sim.init_state(bundle.splats, bundle.scene_context())
        st = sim.step(st, None)
    sp = st.to_splats(bundle.splats)
    rebuilt = covariance_from_scale_rot(sp.scales.double(), sp.quats.double())
    C = 0.5 * (st.covs + st.covs.transpose(-1, -2)).double()
    rel = (rebuilt - C).flatten(1).norm(dim=-1) / C.flatten(1).norm(dim=-1)
    assert float(rel.max()) < 1e-5  # float32 state
