"""000 Example 1: the 14-body chain with clearances at J1, J9, J14 and the prismatic J16 -- the open
system, the blocks of M and of the contact Jacobians (2)-(3), the clearance-free model M_wc of
Sect. 2.2 against the same model built directly, contact LCPs on its Delassus matrices."""
import casadi as ca
import numpy as np
import pytest

import invctl_scenes.chain14 as ch
from invctl.contact.lcp import lcp_residual, lcp_sx, solve_lcp
from invctl.contact.mechanics import ContactSystem
from invctl.contact.reduction import ClearanceFree
from invctl.contact.structure import contact_blocks, open_structure
from invctl.errors import ContactError, ModelError


@pytest.fixture(scope="module")
def chain():
    return ch.build()


@pytest.fixture(scope="module")
def reduction(chain):
    return ClearanceFree(chain, chain.linkage.closure, ch.INDEPENDENT)


def test_open_system_as_stated(chain):
    """15 DoFs in three subsystems of 7, 4, 4 DoFs, m_u = 4 n_pr + n_rev = 7 gaps, 7 actuators
    (000 Example 1, Sect. 2); S1 and S2 underactuated, S3 unactuated (rank E_i < n_i, Sect. 3)."""
    st = open_structure(chain, chain.linkage.nominal)
    assert (st.n, st.n_ind, [s.dof for s in st.subsystems]) == (15, 3, [7, 4, 4])
    assert len(chain.gaps) == 7 and chain.m == 7
    assert [s.status for s in st.subsystems] == ["underactuated", "underactuated", "unactuated"]
    bodies = [set(s.bodies) for s in chain.linkage.subsystems]
    assert bodies == [{f"B{i}" for i in range(1, 8)}, {"B8", "B9", "B10", "B11"}, {"B12", "B13"}]
    assert sum(1 for j in chain.linkage.joints if j.clearance is None and j.kind == "revolute") == 11
    assert sum(1 for j in chain.linkage.joints if j.clearance is None and j.kind == "prismatic") == 1


def test_mass_matrix_is_block_diagonal(chain):
    """M = blockdiag(M1(q1), M2(q2), M3(q3)) at random configurations (entries outside the blocks are
    exactly zero: no coordinate of one subsystem moves a body of another)."""
    rng = np.random.default_rng(3)
    subs = [s.coordinates for s in chain.linkage.subsystems]
    for _ in range(5):
        M = chain.evaluate("M", chain.linkage.nominal + rng.uniform(-0.3, 0.3, chain.n))
        mask = np.zeros_like(M, bool)
        for s in subs:
            mask[np.ix_(s, s)] = True
        assert np.all(M[~mask] == 0.0)
        assert np.all(np.linalg.eigvalsh(M) > 0)


def test_contact_jacobian_pattern_of_3(chain):
    """df_10/dq = (M_10^T, 0, 0), df_12/dq = (M_12^T, M_21^T, 0), df_23/dq = (0, M_23^T, M_32^T),
    df_30/dq = (0, 0, M_30^T) with lam_30 in R^4 (000 (3)): J1 touches S1 and the ground, J9 S1-S2,
    J14 S2-S3, the four gaps of J16 S3 and the ground."""
    q = chain.linkage.nominal + np.random.default_rng(1).uniform(-1e-3, 1e-3, chain.n)
    st = open_structure(chain, q)
    pattern = {name: lab for name, lab, _ in st.contacts}
    assert pattern["J1"] == "S1-ground" and pattern["J9"] == "S1-S2" and pattern["J14"] == "S2-S3"
    assert [lab for name, lab in pattern.items() if name.startswith("J16")] == ["S3-ground"] * 4
    blocks = contact_blocks(chain, q)
    W = ContactSystem(chain).gradients(q)
    for k, b in enumerate(blocks.values()):
        rebuilt = np.zeros(chain.n)
        for s in st.subsystems:
            if s.name in b:
                rebuilt[list(s.coordinates)] = b[s.name]
        np.testing.assert_array_equal(rebuilt, W[:, k])


def test_clearance_free_model_two_ways(chain, reduction):
    """M_wc, f_wc and E_wc from the open system (coordinate partitioning, implicit Omega) equal the
    clearance-free chain built directly with its loops closed in closed form, at the nominal pose and
    at random q_wc; M_wc equals sum_i J_i^T M_i J_i (000's M_1 + dOmega^T blockdiag(M2, M3) dOmega in
    general form).  Tolerance 1e-11 relative: both sides are exact up to the round-off of Newton's
    closure solve (|g| <= 1e-12) and the AD Hessians."""
    direct = ch.direct_clearance_free()
    rng = np.random.default_rng(0)
    qn = chain.linkage.nominal
    subs = [s.coordinates for s in chain.linkage.subsystems]
    for k in range(5):
        qwc = qn[ch.INDEPENDENT] + (0 if k == 0 else rng.uniform(-0.02, 0.02, 7))
        q = reduction.configuration(qwc, qn)
        assert reduction.residual(q) <= 1e-12
        Md = direct.evaluate("M", qwc)
        Mw = reduction.mass_matrix(q)
        np.testing.assert_allclose(Mw, Md, rtol=0, atol=1e-11 * np.abs(Md).max())
        np.testing.assert_allclose(sum(reduction.blocks(q, subs)), Mw, atol=1e-13 * np.abs(Md).max())
        v = rng.normal(size=7)
        fd = direct.evaluate("f", qwc, v).ravel()
        np.testing.assert_allclose(reduction.forces(q, v), fd, atol=1e-11 * max(1.0, np.abs(fd).max()))
        np.testing.assert_allclose(reduction.input_matrix(q), np.eye(7), atol=1e-13)
    assert reduction.assumption1(qn)["holds"]


def test_clearance_free_with_gravity(chain):
    """The potential forces too: with g = 9.81 the reduced generalized forces at rest equal the direct
    model's -dU/dq_wc."""
    m = ch.build(g=9.81)
    cf = ClearanceFree(m, m.linkage.closure, ch.INDEPENDENT)
    direct = ch.direct_clearance_free(g=9.81)
    qn = m.linkage.nominal
    fd = direct.evaluate("f", qn[ch.INDEPENDENT]).ravel()
    np.testing.assert_allclose(cf.forces(qn, np.zeros(7)), fd, atol=1e-12 * np.abs(fd).max())
    assert np.abs(fd).max() > 0.1


def test_inertia_is_redistributed(chain, reduction):
    """000 Sect. 2.2: M_1(q_wc) != M_wc(q_wc) -- closing the clearances adds the inertia of S2, S3 (and
    of B6, B7) to the independent coordinates."""
    qn = chain.linkage.nominal
    M1 = chain.evaluate("M", qn)[:5, :5]
    assert np.abs(reduction.mass_matrix(qn)[:5, :5] - M1).max() > 1e-2 * np.abs(M1).max()


def test_reduction_reports_bad_input(chain):
    with pytest.raises(ModelError, match="closure constraints for"):
        ClearanceFree(chain, chain.linkage.closure, ch.INDEPENDENT[:-1])
    cf = ClearanceFree(chain, chain.linkage.closure, ch.INDEPENDENT)
    with pytest.raises(ContactError) as exc:
        cf.configuration(chain.linkage.nominal[ch.INDEPENDENT] + 1.0, chain.linkage.nominal)
    assert exc.value.partial is not None and "can be assembled" in str(exc.value)


def test_contact_lcps_on_the_chain(chain):
    """Contact LCPs (7) with the chain's Delassus matrix of the journals J1, J9, J14 and two opposite
    corners of the slider (J16 front top, back bottom: contacts that can be closed together; the four
    corner gaps of one prismatic joint span only two directions, so all seven are dependent) -- a
    P-matrix (Assumption 2) -- and random right-hand sides: the compiled block-pivoting and Lemke
    solvers agree with the numpy enumeration to 1e-10 (1 + |z|) and satisfy complementarity."""
    rng = np.random.default_rng(5)
    cs = ContactSystem(chain)
    active = [0, 1, 2, 3, 6]
    q = chain.linkage.nominal + rng.uniform(-2e-3, 2e-3, chain.n)
    assert np.linalg.matrix_rank(cs.delassus(q)) == 5          # all seven: rank 3 + 2
    A_s, b_s = ca.SX.sym("A", 5, 5), ca.SX.sym("b", 5)
    solvers = {m: ca.Function(m, [A_s, b_s], list(lcp_sx(A_s, b_s, method=m, with_flag=True)))
               for m in ("pivoting", "lemke")}
    for _ in range(8):
        q = chain.linkage.nominal + rng.uniform(-2e-3, 2e-3, chain.n)
        D = cs.delassus(q, active)
        assert np.linalg.eigvalsh(0.5 * (D + D.T)).min() > 0
        b = rng.normal(size=5) * np.abs(D).max()
        ref = solve_lcp(D, b, method="enumeration")
        for fn in solvers.values():
            z, ok = (np.array(x).ravel() for x in fn(D, b))
            assert ok[0] == 1
            np.testing.assert_allclose(z, ref.z, atol=1e-10 * (1 + np.abs(ref.z).max()))
            assert lcp_residual(D, b, z) <= 1e-10 * (1 + np.abs(b).max())


def test_compiled_steps_match_numpy_steps(chain):
    """300 compiled Moreau-Jean steps of the chain under PD (36) (7 contacts: block pivoting inside the
    step) equal the same steps with numpy Lemke LCPs to 1e-11, and V (37) never increases over 0.3 s."""
    from invctl.control.pdplus import pd_gravity, selection_indices
    from invctl.simulate.timestepping import MoreauJean

    idx = selection_indices(chain)
    law = pd_gravity(chain, Kp=5.0, Kv=0.5, q_d=chain.linkage.nominal[idx] + 0.05, idx=idx)
    mj = MoreauJean(chain, law, backend="vm")
    q0, v0 = chain.linkage.nominal, np.zeros(chain.n)
    tr = mj.run(q0, v0, 0.3, 1e-3)
    Q, _ = mj.reference_run(q0, v0, 300, 1e-3)
    assert np.abs(tr.q - Q).max() <= 1e-11
    assert tr.stats["n_impacts"] >= 1 and tr.max_V_increase <= 1e-12 * tr.V[0]
