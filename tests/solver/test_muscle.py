"""Active transversely isotropic muscle law: tangent, energy, and analytic fibre responses."""
import numpy as np
import pytest

from solver.constitution.muscle import Muscle, force_length
from solver.errors import MaterialError


def _muscle(activation=0.6, **kw):
    p = dict(C10=2.5, C20=1.175, C30=0.5, K=250.0, k1=5.0, k2=4.0, T_max=100.0,
             lam_opt=1.05, width=0.5, G_T=1.0, G_T_active=20.0, activation=activation)
    p.update(kw)
    return Muscle(**p)


def _random_C(rng, n=6, amp=0.25):
    F = np.eye(3) + amp * rng.standard_normal((n, 3, 3))
    F[np.linalg.det(F) < 0.2] = np.eye(3)
    return np.einsum("nki,nkj->nij", F, F)


def _random_fibres(rng, n):
    a = rng.standard_normal((n, 3))
    return a / np.linalg.norm(a, axis=1, keepdims=True)


@pytest.mark.parametrize("load", [0.0, 0.5, 1.0])
def test_stress_is_energy_derivative_and_tangent_is_stress_derivative(load):
    rng = np.random.default_rng(1)
    C = _random_C(rng)
    # some points stretched along the fibre, to exercise the passive exponential branch
    a0 = _random_fibres(rng, len(C))
    C[:2] += 0.3 * np.einsum("ni,nj->nij", a0[:2], a0[:2])
    mat = _muscle()
    S, CC, W = mat.isochoric(C, a0, load)
    h = 1e-6
    dS_fd = np.zeros_like(CC)
    dW_fd = np.zeros_like(S)
    for i in range(3):
        for j in range(3):
            E = np.zeros((3, 3))
            E[i, j] += 0.5 * h
            E[j, i] += 0.5 * h
            Sp, _, Wp = mat.isochoric(C + E, a0, load)
            Sm, _, Wm = mat.isochoric(C - E, a0, load)
            dW_fd[:, i, j] = (Wp - Wm) / (2 * h)
            dS_fd[:, :, :, i, j] = (Sp - Sm) / (2 * h)
    # central differences with h = 1e-6 on O(10-100) kPa quantities: truncation ~h^2 * W''',
    # round-off ~1e-16 * 100 / 1e-6 = 1e-8; 1e-5 relative is a wide but failing-capable margin.
    scale = np.abs(S).max()
    assert np.abs(2.0 * dW_fd - S).max() < 1e-5 * scale
    assert np.abs(2.0 * dS_fd - CC).max() < 1e-5 * np.abs(CC).max()
    # major and minor symmetry of the tangent
    assert np.allclose(CC, np.swapaxes(np.swapaxes(CC, 1, 3), 2, 4), atol=1e-9 * scale)
    assert np.allclose(CC, np.swapaxes(CC, 1, 2), atol=1e-9 * scale)


def test_reference_state_is_stress_free_at_zero_activation():
    a0 = np.array([[0.0, 0.0, 1.0]])
    S, _, W = _muscle(activation=0.0).isochoric(np.eye(3)[None], a0)
    assert np.abs(S).max() < 1e-12 and abs(W[0]) < 1e-12


def _uniaxial_cauchy(mat, lam, load=1.0):
    """Incompressible uniaxial state along e1: sigma_11 - sigma_22 from the material's S."""
    F = np.diag([lam, lam ** -0.5, lam ** -0.5])
    C = F.T @ F
    S, _, _ = mat.isochoric(C[None], np.array([[1.0, 0.0, 0.0]]), load)
    sigma = F @ S[0] @ F.T  # J = 1
    return sigma[0, 0] - sigma[1, 1], sigma


@pytest.mark.parametrize("lam", [0.8, 0.95, 1.0, 1.1, 1.3])
def test_uniaxial_fibre_stress_is_matrix_plus_passive_plus_active(lam):
    """Along-fibre uniaxial stress equals 2 W1 (l^2 - 1/l) + sigma_passive + a T_max f(l) l/l_opt."""
    mat = _muscle(activation=0.7)
    s_fe, sigma = _uniaxial_cauchy(mat, lam)
    C10, C20, C30 = 2.5, 1.175, 0.5
    t = lam ** 2 + 2 / lam - 3
    matrix = 2 * (C10 + 2 * C20 * t + 3 * C30 * t * t) * (lam ** 2 - 1 / lam)
    s = max(lam ** 2 - 1.0, 0.0)
    passive = 2 * lam ** 2 * 5.0 * s * np.exp(4.0 * s * s)
    active = 0.7 * 100.0 * np.exp(-(np.log(lam / 1.05) / 0.5) ** 2) * lam / 1.05
    # closed-form evaluation of the same expression: agreement to round-off (1e-9 relative)
    assert s_fe == pytest.approx(matrix + passive + active, rel=1e-9, abs=1e-9)
    assert mat.uniaxial_fibre_stress(lam) == pytest.approx(s_fe, rel=1e-9, abs=1e-9)
    # the lateral faces carry the same deviatoric stress: transversely isotropic state
    assert sigma[1, 1] == pytest.approx(sigma[2, 2], abs=1e-9)
    assert abs(sigma[1, 2]) < 1e-9


def test_active_stress_scales_with_activation_and_load():
    lam = 1.0
    base = _muscle(activation=0.0)
    s0, _ = _uniaxial_cauchy(base, lam)
    for a, load in [(1.0, 1.0), (0.5, 1.0), (1.0, 0.25)]:
        s, _ = _uniaxial_cauchy(_muscle(activation=a), lam, load)
        f = force_length(lam, 1.05, 0.5)
        assert s - s0 == pytest.approx(a * load * 100.0 * f * lam / 1.05, rel=1e-12)


@pytest.mark.parametrize("a", [0.2, 0.5, 1.0])
def test_activation_never_softens_the_fibres_below_their_optimal_length(a):
    """The nominal (force per reference area) fibre stress follows the force-length relation,
    so on the ascending limb lam <= lam_opt activation adds along-fibre stiffness and at lam_opt
    none. A Cauchy-proportional active stress would subtract a T_max / lam_opt^2 there: with
    the face's matrix (3 mu = 15 kPa) and T_max = 100 kPa, a tone above ~0.17 would make the
    along-fibre tangent negative at rest length and a muscle collapse onto itself."""
    face = dict(C10=2.5, C20=1.175, C30=0.0, K=5000.0, k1=2.0, k2=5.0, T_max=100.0,
                lam_opt=1.0, width=0.5, G_T=0.0, G_T_active=20.0)
    lam = np.linspace(0.6, 1.0, 401)
    h = 1e-6

    def slope(mat):
        # central difference of P = sigma / lam; h = 1e-6 on O(10-100) kPa: error < 1e-6 kPa
        P = lambda s: mat.uniaxial_fibre_stress(s) / s
        return (P(lam + h) - P(lam - h)) / (2 * h)

    active, passive = slope(Muscle(**face, activation=a)), slope(Muscle(**face, activation=0.0))
    assert passive.min() > 0.0
    assert np.all(active >= passive - 1e-5)            # 1e-5 kPa: the differences' round-off
    # at lam_opt the active part's slope is zero: the same tangent as the passive muscle
    assert active[-1] == pytest.approx(passive[-1], abs=1e-4)
    # below it the active part stiffens: a T_max f'(lam) / lam_opt, f' > 0 on the ascending limb
    k = np.searchsorted(lam, 0.9)
    f1 = force_length(lam[k], 1.0, 0.5) * (-2.0 * np.log(lam[k]) / 0.25) / lam[k]
    assert active[k] - passive[k] == pytest.approx(a * 100.0 * f1, rel=1e-4)


def test_lateral_term_stiffens_cross_fibre_shear_with_activation_but_not_fibre_stretch():
    """Simple shear across the fibres: shear stress slope grows by G_T_active * a."""
    gamma = 1e-4
    F = np.eye(3)
    F[1, 2] = gamma  # shear in the plane normal to the fibre e1
    C = (F.T @ F)[None]
    a0 = np.array([[1.0, 0.0, 0.0]])
    out = []
    for a in (0.0, 1.0):
        mat = _muscle(activation=a, T_max=0.0, k1=0.0)
        S, _, _ = mat.isochoric(C, a0)
        out.append(S[0, 1, 2] / gamma)
    # small-strain shear modulus across fibres: 2 C10 + mu_T(a); d(mu)/da = G_T_active = 20
    # (linearisation error O(gamma) = 1e-4 relative)
    assert out[0] == pytest.approx(2 * 2.5 + 1.0, rel=1e-3)
    assert out[1] - out[0] == pytest.approx(20.0, rel=1e-3)
    # pure fibre stretch: no contribution of the lateral term
    m0 = _muscle(activation=0.0, T_max=0.0, k1=0.0, G_T=0.0, G_T_active=0.0)
    m1 = _muscle(activation=1.0, T_max=0.0, k1=0.0, G_T=3.0, G_T_active=20.0)
    assert _uniaxial_cauchy(m1, 0.9)[0] == pytest.approx(_uniaxial_cauchy(m0, 0.9)[0], rel=1e-12)


def test_elements_without_fibres_are_the_isotropic_matrix():
    rng = np.random.default_rng(3)
    C = _random_C(rng, 4)
    S, CC, W = _muscle(activation=1.0).isochoric(C, np.zeros((4, 3)))
    S2, CC2, W2 = _muscle(activation=0.0, T_max=0.0, k1=0.0, G_T=0.0,
                          G_T_active=0.0).isochoric(C, np.zeros((4, 3)))
    assert np.allclose(S, S2, atol=1e-12) and np.allclose(CC, CC2, atol=1e-12)
    assert np.allclose(W, W2, atol=1e-12)


@pytest.mark.parametrize("bad", [dict(C10=-1.0), dict(activation=1.5), dict(T_max=np.nan),
                                 dict(k2=0.0)])
def test_bad_parameters_are_refused(bad):
    with pytest.raises(MaterialError):
        _muscle(**bad)


@pytest.mark.parametrize("law", ["muscle", "yeoh"])
def test_stress_without_tangent_is_the_same_stress(law):
    # a residual or stress evaluation skips the fourth-order tensor: S and W must be those of
    # the full evaluation (the same expressions, so to round-off, 1e-12 relative)
    from solver.constitution import Yeoh

    rng = np.random.default_rng(7)
    C = _random_C(rng, n=8)
    a0 = _random_fibres(rng, len(C))
    mat = _muscle() if law == "muscle" else Yeoh(C10=2.5, C20=1.175, C30=0.5, K=250.0)
    S, CC, W = mat.isochoric(C, a0, 0.7)
    S2, CC2, W2 = mat.isochoric(C, a0, 0.7, tangent=False)
    assert CC is not None and CC2 is None
    assert np.allclose(S2, S, rtol=1e-12, atol=0.0) and np.allclose(W2, W, rtol=1e-12, atol=0.0)
