"""Losses of paper 1, Table 1: ψ = ρ′, φ = ψ/x, finite weights at 0, name parsing."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.averaging.losses import LOSS_NAMES, get_loss

NAMES = ["l2", "l1", "l0.5", "l1.5", "geman-mcclure", "huber", "pseudo-huber", "andrews",
         "bisquare", "cauchy", "fair", "logistic", "talwar", "welsch"]
ALPHA_DEG = 5.0


def _grid(loss) -> np.ndarray:
    """Residuals in (0, 0.6] rad away from the kinks at α, απ and the floor."""
    x = np.linspace(1e-3, 0.6, 400)
    a = loss.alpha_rad
    kinks = np.array([a, a * np.pi, loss.eps_rad])
    far = np.min(np.abs(x[:, None] - kinks[None, :]), axis=1) > 2e-4
    return x[far]


@pytest.mark.parametrize("name", NAMES)
def test_psi_is_derivative_of_rho(name):
    loss = get_loss(name, ALPHA_DEG)
    x = _grid(loss)
    h = 1e-6
    fd = (loss.rho(x + h) - loss.rho(x - h)) / (2 * h)
    psi = loss.psi(x)
    np.testing.assert_allclose(fd, psi, rtol=1e-5, atol=1e-8)


@pytest.mark.parametrize("name", NAMES)
def test_phi_is_psi_over_x(name):
    loss = get_loss(name, ALPHA_DEG)
    x = _grid(loss)
    np.testing.assert_allclose(loss.phi(x) * x, loss.psi(x), rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("name", NAMES)
def test_weights_finite_and_nonnegative_at_zero(name):
    loss = get_loss(name, ALPHA_DEG)
    x = np.array([0.0, 1e-300, 1e-12, 1e-6, 3.0, np.pi])
    w = loss.phi(x)
    assert np.all(np.isfinite(w)) and np.all(w >= 0)
    assert np.all(np.isfinite(loss.rho(x))) and np.all(np.isfinite(loss.psi(x)))


def test_floor_below_eps_is_quadratic_and_c1():
    loss = get_loss("l0.5", ALPHA_DEG, eps_rad=1e-3)
    x = np.array([1e-4, 5e-4])
    np.testing.assert_allclose(loss.phi(x), (1e-3) ** -1.5)
    # Continuity of ρ and ψ across the floor.
    e = 1e-3
    assert abs(loss.rho(e - 1e-12) - loss.rho(e + 1e-12)) < 1e-9
    assert abs(loss.psi(e - 1e-12) - loss.psi(e + 1e-12)) < 1e-6


def test_default_floor_is_alpha_for_p_below_one_and_tiny_for_l1():
    assert get_loss("l0.5", 5.0).eps_rad == pytest.approx(np.deg2rad(5.0))
    assert get_loss("l1", 5.0).eps_rad < 1e-5


def test_table_values_at_a_point():
    a = np.deg2rad(5.0)
    x = np.array([0.5 * a])
    assert get_loss("geman-mcclure").rho(x)[0] == pytest.approx(0.5 * x[0] ** 2 / (a * a + x[0] ** 2))
    assert get_loss("cauchy").phi(x)[0] == pytest.approx(1 / (1 + 0.25))
    assert get_loss("welsch").phi(x)[0] == pytest.approx(np.exp(-0.25))
    assert get_loss("huber").phi(np.array([2 * a]))[0] == pytest.approx(0.5)
    assert get_loss("talwar").phi(np.array([2 * a]))[0] == 0.0
    assert get_loss("bisquare").phi(np.array([2 * a]))[0] == 0.0
    assert get_loss("l2").phi(x)[0] == 1.0
    # the other seven against paper 1's ψ (Table 1), as weights φ = ψ/x at x = α/2 (and 2α beyond a floor of α)
    assert get_loss("andrews").phi(x)[0] == pytest.approx(np.sin(0.5) / 0.5)
    assert get_loss("fair").phi(x)[0] == pytest.approx(1 / 1.5)
    assert get_loss("logistic").phi(x)[0] == pytest.approx(np.tanh(0.5) / 0.5)
    assert get_loss("pseudo-huber").phi(x)[0] == pytest.approx(1 / np.sqrt(1.25))
    assert get_loss("l1").phi(np.array([0.1]))[0] == pytest.approx(10.0)
    assert get_loss("l1.5").phi(np.array([0.1]))[0] == pytest.approx(0.1 ** -0.5)
    assert get_loss("l0.5").phi(np.array([2 * a]))[0] == pytest.approx((2 * a) ** -1.5)
    assert get_loss("andrews").phi(np.array([4 * a]))[0] == 0.0  # beyond απ


def test_alpha_is_in_degrees():
    assert get_loss("huber", 10.0).alpha_rad == pytest.approx(np.deg2rad(10.0))


@pytest.mark.parametrize("name,canon", [("l0.5", "l0.5"), ("L0.25", "l0.25"), ("l1", "l1"), ("l2", "l2"),
                                        ("lp0.5", "l0.5"), ("GM", "geman-mcclure"), ("Pseudo_Huber", "pseudo-huber")])
def test_name_parsing(name, canon):
    assert get_loss(name).name == canon


def test_lp_matches_formula():
    loss = get_loss("l0.25", eps_rad=1e-9)
    x = np.array([0.1, 0.3])
    np.testing.assert_allclose(loss.rho(x), x**0.25 / 0.25)
    np.testing.assert_allclose(loss.phi(x), x ** (0.25 - 2))


def test_unknown_loss_lists_valid_names():
    with pytest.raises(ValueError, match="unknown loss 'hubr'.*geman-mcclure.*welsch"):
        get_loss("hubr")


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan")])
def test_bad_alpha_rejected(bad):
    with pytest.raises(ValueError, match="alpha_deg"):
        get_loss("huber", bad)


def test_l0_rejected():
    with pytest.raises(ValueError, match="p must be > 0"):
        get_loss("l0")


def test_bad_floor_rejected():
    with pytest.raises(ValueError, match="eps_rad"):
        get_loss("l1", 5.0, eps_rad=0.0)


def test_loss_names_listed():
    assert len(LOSS_NAMES) == 13
