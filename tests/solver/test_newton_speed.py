"""Lagged-factor inexact Newton (`linear_strategy="lagged"`): the same converged solution as
exact Newton with fewer factorisations, and Krylov iterations / refactorisations in the log.

Both runs stop at |R_free| <= 1e-10 |f_int| on a Yeoh block pulled 40% in two steps. Two
displacement fields that both satisfy that residual bound differ by at most about
cond(K) * 1e-10 relative; the block's condensed tangent has a condition number of order 1e3
(K/C10 = 40, a 4x4x4 mesh), so 1e-6 relative is a safe bound that a wrong solution (any O(1)
error in the Newton system, e.g. a stale tangent used as if exact without the Krylov correction
on the fresh one) would exceed by orders of magnitude.
"""
import numpy as np
import pytest

import solver
from solver.examples import block


def _pull(strategy, steps=2, etol=1e-14, **kw):
    nodes, hexes, s = block((4.0, 4.0, 4.0), (4, 4, 4))
    body = solver.SolidBody(solver.HexMesh(nodes, hexes),
                            solver.Yeoh(2.5, 1.175, 0.0, K=100.0, volumetric="quadratic"))
    bcs = [solver.fix(s["xmin"]), solver.Prescribed(s["xmax"], [1.6, 0.0, 0.0], (0,))]
    return solver.newton_solve(body, bcs, steps=steps, grow=False, rtol=1e-10, etol=etol,
                               linear_strategy=strategy, **kw)


@pytest.fixture(scope="module")
def runs():
    return _pull("exact"), _pull("lagged", krylov_rtol=1e-10, krylov_maxiter=30)


def test_lagged_reaches_exact_solution(runs):
    exact, lagged = runs
    assert exact.converged and lagged.converged
    rel = np.abs(lagged.u - exact.u).max() / np.abs(exact.u).max()
    assert rel < 1e-6, rel
    # reactions are the residual at the constrained dofs: same to the same bound
    assert np.allclose(lagged.reactions, exact.reactions,
                       atol=1e-6 * np.abs(exact.reactions).max())


def test_lagged_saves_factorisations_and_logs_krylov(runs):
    exact, lagged = runs
    assert exact.factorizations == exact.iterations          # one per Newton iteration
    assert exact.krylov_iterations == 0
    assert lagged.factorizations < exact.factorizations
    assert lagged.krylov_iterations > 0
    recs = lagged.log
    assert all("krylov_iterations" in r and "factorized" in r for r in recs)
    # the first system is factorised; with the single-precision preconditioner factor CG
    # still takes a few iterations on it (one or more)
    assert recs[0]["factorized"] and recs[0]["krylov_iterations"] >= 1
    assert sum(r["krylov_iterations"] for r in recs) == lagged.krylov_iterations
    # the log counts the factorisations too (a refactorisation may follow failed CG sweeps)
    assert sum(r["factorized"] for r in recs) == lagged.factorizations
    assert all(r["factorized"] and r["krylov_iterations"] == 0 for r in exact.log)


def test_stale_factor_forces_refactorisation():
    # with no Krylov iterations allowed every iteration must refactorise: exact Newton again
    res = _pull("lagged", krylov_rtol=1e-10, krylov_maxiter=0)
    assert res.converged
    assert res.factorizations == res.iterations


def test_secant_predictor_same_solution_fewer_iterations():
    # the extrapolated start only changes where Newton starts: the converged state satisfies
    # the same residual bound (1e-10 relative), hence the same 1e-6 bound as above; on this
    # smooth pull it saves iterations
    # (four steps, so that the third and fourth extrapolate quadratically; residual-only
    # convergence test, etol = 1, as the energy ratio is relative to the step's first
    # iteration, which a good predictor makes small)
    kw = dict(steps=4, etol=1.0)
    tangent = _pull("exact", predictor="tangent", **kw)
    secant = _pull("exact", predictor="secant", **kw)
    assert tangent.converged and secant.converged
    rel = np.abs(secant.u - tangent.u).max() / np.abs(tangent.u).max()
    assert rel < 1e-6, rel
    assert secant.iterations < tangent.iterations
    # the first step has no history: same iterations as the tangent predictor there
    assert secant.steps[0].iterations == tangent.steps[0].iterations


def test_double_precision_preconditioner_and_auto_predictor():
    # an exact (double-precision) Cholesky factor of the current tangent solves its system in
    # one CG iteration; the same converged solution as exact Newton (bound as above)
    exact = _pull("exact")
    res = _pull("lagged", krylov_rtol=1e-10, krylov_precision="double")
    assert res.converged
    assert res.log[0]["factorized"] and res.log[0]["krylov_iterations"] == 1
    rel = np.abs(res.u - exact.u).max() / np.abs(exact.u).max()
    assert rel < 1e-6, rel


def test_bad_options_refused():
    with pytest.raises(ValueError):
        _pull("lagged", predictor="quadratic")
    with pytest.raises(ValueError):
        _pull("lagged", krylov_precision="half")


def _block_with_far_plane():
    """A 2x2x2 Yeoh block with a contact term that never acts (a rigid plane 0.5 mm beyond
    its top, searched within 0.1 mm) and a pull of 0.05 on its +x face's nodes: (body, node
    sets, term, force)."""
    from solver.contact import RigidSurfaceContact

    nodes, hexes, s = block((4.0, 4.0, 4.0), (2, 2, 2))
    plane = np.array([[-9.0, -9.0, 4.5], [9.0, -9.0, 4.5], [9.0, 9.0, 4.5], [-9.0, 9.0, 4.5]])
    far = RigidSurfaceContact(nodes, plane, np.array([[0, 2, 1], [0, 3, 2]]),
                              slave_nodes=s["zmax"], search_radius=0.1)
    body = solver.SolidBody(solver.HexMesh(nodes, hexes),
                            solver.Yeoh(2.5, 1.175, 0.0, K=100.0, volumetric="quadratic"))
    f = np.zeros(3 * len(nodes))
    f[3 * s["xmax"]] = 0.05
    return body, s, far, f


def test_auto_predictor_is_tangent_for_terms_under_prescribed_motion():
    # "auto" takes the secant predictor with the lagged strategy, but the tangent predictor
    # when extra terms (contact) act under prescribed motion (surfaces that move with the
    # bones make the extrapolated start a poor one); the choice is recorded
    assert _pull("lagged").predictor == "secant"
    assert _pull("exact").predictor == "tangent"
    body, s, far, f = _block_with_far_plane()
    pulled = [solver.fix(s["xmin"]), solver.Prescribed(s["xmax"], [0.4, 0.0, 0.0], (0,))]
    res = solver.newton_solve(body, pulled, [far], steps=2, linear_strategy="lagged")
    assert res.converged and res.predictor == "tangent"
    res = solver.newton_solve(body, [solver.fix(s["xmin"])], [far], external=f, steps=2,
                              linear_strategy="lagged")
    assert res.converged and res.predictor == "secant"


def test_extrapolation_is_linear_with_terms_quadratic_without(monkeypatch):
    # contact switching on kinks the load path, where a parabola overshoots: with extra
    # terms the secant predictor extrapolates through the last two converged states only
    import solver.newton as newton

    points = []
    exact = newton._extrapolate

    def counting(history, target):
        points.append(len(history))
        return exact(history, target)

    monkeypatch.setattr(newton, "_extrapolate", counting)
    body, s, far, f = _block_with_far_plane()
    for terms, most in (([far], 2), ([], 3)):
        points.clear()
        res = solver.newton_solve(body, [solver.fix(s["xmin"])], terms, external=f, steps=4,
                                  grow=False, linear_strategy="lagged")
        assert res.converged and res.predictor == "secant"
        assert max(points) == most, points


def test_a_bad_extrapolated_start_is_rejected_for_the_tangent_predictor(monkeypatch):
    # An extrapolation ten times too long (the converged state of the last step plus ten
    # times its increment) leads Newton astray: the step is solved again from its converged
    # start with the tangent predictor instead of being cut back, and reaches the same
    # solution (the 1e-6 bound of the tests above)
    import solver.newton as newton

    exact = newton._extrapolate

    def ten_times(history, target):
        x, mixed = exact(history, target)
        last = history[-1][1]
        return last + 10.0 * (x - last), mixed

    tangent = _pull("exact", predictor="tangent", steps=4, etol=1.0)
    monkeypatch.setattr(newton, "_extrapolate", ten_times)
    res = _pull("exact", predictor="secant", steps=4, etol=1.0)
    assert res.converged and res.cutbacks == 0
    assert res.predictor_rejections >= 1
    rel = np.abs(res.u - tangent.u).max() / np.abs(tangent.u).max()
    assert rel < 1e-6, rel
