"""Noise models against closed forms written out here, not taken from the code."""

import dataclasses

import numpy as np
import pytest

from fluxcli.imaging.noise import (
    EMCCDModel,
    PhotonNoise,
    counts_to_photons,
    emccd_counts,
    expected_counts,
    expected_variance_counts,
    gaussian_shot,
    max_snr,
    poisson_shot,
    saturated,
)

FLAT_SHAPE = (512, 512)


def flat(photons):
    return np.full(FLAT_SHAPE, float(photons))


def mean_input_electrons(photons, m):
    """λ = QE·N + dark·t + CIC, written out independently of the module."""
    dark_e = m.dark_current_e_per_s * m.exposure_s
    return m.quantum_efficiency * photons + dark_e + m.cic_e_per_pixel


@pytest.mark.parametrize(
    "photons, model",
    [
        (200.0, EMCCDModel(em_gain=300.0)),  # the defaults: read noise 50 e-, 10 e-/count
        (5.0, EMCCDModel(em_gain=1000.0, read_noise_e=5.0)),  # photon-starved, high gain
        # Unit gain: no multiplication, F² = 1 (a conventional readout).
        (200.0, EMCCDModel(em_gain=1.0, read_noise_e=0.1, electrons_per_count=0.05)),
        # Low gain, where F² = 2 − 1/G (1.5) and the high-gain 2 differ by a third.
        (200.0, EMCCDModel(em_gain=2.0, read_noise_e=0.1, electrons_per_count=0.05)),
    ],
)
def test_emccd_flat_field_mean_and_excess_noise(photons, model):
    counts = emccd_counts(flat(photons), model, np.random.default_rng(1))
    assert counts.dtype == np.uint16 and counts.shape == FLAT_SHAPE
    assert not saturated(counts, model).any()

    lam = mean_input_electrons(photons, model)
    g, gain = model.electrons_per_count, model.em_gain
    mean_closed = model.bias_counts + gain * lam / g
    f2 = 2 - 1 / gain  # ideal multiplication (many stages): Robbins & Hadwen 2003
    var_closed = f2 * gain**2 * lam / g**2 + (model.read_noise_e / g) ** 2
    assert counts.mean() == pytest.approx(mean_closed, rel=0.03)
    assert counts.var() == pytest.approx(var_closed, rel=0.03)
    np.testing.assert_allclose(expected_counts(photons, model), mean_closed, rtol=1e-12)
    np.testing.assert_allclose(expected_variance_counts(photons, model), var_closed, rtol=1e-12)

    # Excess noise factor of the EM register, read noise subtracted.
    electrons = (counts.astype(np.float64) - model.bias_counts) * g
    excess_noise_factor_sq = (electrons.var() - model.read_noise_e**2) / (gain * electrons.mean())
    assert excess_noise_factor_sq == pytest.approx(f2, rel=0.03)


@pytest.mark.parametrize("gain", [1.0, 2.0, 300.0])
def test_photon_noise_model_is_the_variance_of_the_simulated_chain(gain):
    """The reconstruction's EMCCD noise model is the variance of what the simulator makes, read
    back as photons: σ² = [F²(QE·a + d) + (σ_r/G)²] / QE², F² = 2 − 1/G, written out here and
    compared with the sample variance of counts_to_photons(emccd_counts(a))."""
    model = EMCCDModel(em_gain=gain, read_noise_e=0.1 * gain, electrons_per_count=0.05 * gain)
    photons = 200.0
    noise = PhotonNoise(kind="emccd", sensor=model, floor_photons2=0.0)
    qe, d = model.quantum_efficiency, mean_input_electrons(0.0, model)
    closed = ((2 - 1 / gain) * (qe * photons + d) + (model.read_noise_e / gain) ** 2) / qe**2
    assert float(noise.variance(photons)) == pytest.approx(closed, rel=1e-12)
    back = counts_to_photons(emccd_counts(flat(photons), model, np.random.default_rng(11)), model)
    assert back.var() == pytest.approx(closed, rel=0.03)


def test_emccd_no_electrons_gives_bias_exactly():
    model = EMCCDModel(read_noise_e=0.0, dark_current_e_per_s=0.0, cic_e_per_pixel=0.0)
    counts = emccd_counts(np.zeros((16, 16)), model, np.random.default_rng(0))
    assert np.all(counts == 500)


def test_emccd_clips_below_zero():
    model = EMCCDModel(bias_counts=0.0, read_noise_e=100.0)
    counts = emccd_counts(np.zeros((64, 64)), model, np.random.default_rng(0))
    assert counts.min() == 0  # half the pixels would be negative without the clip


@pytest.mark.parametrize("noise", [poisson_shot, gaussian_shot])
def test_shot_noise_variance_equals_mean(noise):
    photons = noise(flat(200.0), np.random.default_rng(2))
    assert photons.dtype == np.float64 and photons.shape == FLAT_SHAPE
    assert photons.mean() == pytest.approx(200.0, rel=0.01)
    assert photons.var() == pytest.approx(photons.mean(), rel=0.03)


def test_poisson_shot_is_integer_valued_and_gaussian_can_go_negative():
    rng = np.random.default_rng(3)
    poisson = poisson_shot(flat(0.5), rng)
    assert np.array_equal(poisson, np.round(poisson)) and poisson.min() == 0
    assert gaussian_shot(flat(0.5), rng).min() < 0  # as in the paper: not clipped


def test_saturation_clips_and_is_flagged():
    model = EMCCDModel()
    photons = np.full((8, 8), 100.0)
    photons[2, 5] = 1e6
    counts = emccd_counts(photons, model, np.random.default_rng(4))
    assert counts[2, 5] == 65535
    mask = saturated(counts, model)
    expected_mask = np.zeros((8, 8), bool)
    expected_mask[2, 5] = True
    np.testing.assert_array_equal(mask, expected_mask)


def test_saturation_follows_bit_depth():
    model = EMCCDModel(bit_depth=12)
    counts = emccd_counts(np.full((4, 4), 1e6), model, np.random.default_rng(5))
    assert np.all(counts == 4095) and saturated(counts, model).all()


def test_counts_to_photons_recovers_photons_from_mean_counts():
    model = EMCCDModel()
    counts = emccd_counts(flat(200.0), model, np.random.default_rng(6))
    assert counts_to_photons(counts.mean(), model) == pytest.approx(200.0, rel=0.01)
    # Per-pixel estimates are unbiased: their average is right too.
    assert counts_to_photons(counts, model).mean() == pytest.approx(200.0, rel=0.01)


def test_counts_to_photons_inverts_closed_form_mean():
    model = EMCCDModel(quantum_efficiency=0.7, em_gain=50.0, cic_e_per_pixel=0.02, exposure_s=3.0)
    photons = np.array([[0.0, 1.0], [37.5, 1e4]])
    lam = mean_input_electrons(photons, model)
    mean_counts = model.bias_counts + model.em_gain * lam / model.electrons_per_count
    np.testing.assert_allclose(counts_to_photons(mean_counts, model), photons, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize(
    "simulate",
    [
        lambda a, rng: emccd_counts(a, EMCCDModel(), rng),
        poisson_shot,
        gaussian_shot,
    ],
    ids=["emccd", "poisson", "gaussian"],
)
def test_same_seed_same_bytes(simulate):
    photons = np.linspace(0.0, 500.0, 64 * 48).reshape(64, 48)
    first = simulate(photons, np.random.default_rng(123)).tobytes()
    again = simulate(photons, np.random.default_rng(123)).tobytes()
    other = simulate(photons, np.random.default_rng(124)).tobytes()
    assert first == again
    assert first != other


def test_max_snr_is_sqrt_of_brightest_pixel():
    assert max_snr(np.array([[1.0, 4.0], [100.0, 9.0]])) == pytest.approx(10.0)


@pytest.mark.parametrize(
    "field, value",
    [
        ("quantum_efficiency", 0.0),
        ("quantum_efficiency", 1.2),
        ("em_gain", 0.5),
        ("read_noise_e", -1.0),
        ("bias_counts", -1.0),
        ("electrons_per_count", 0.0),
        ("dark_current_e_per_s", -0.1),
        ("cic_e_per_pixel", -0.1),
        ("exposure_s", -1.0),
        ("exposure_s", float("nan")),
        ("em_gain", float("inf")),
        ("em_gain", "300"),
        ("bit_depth", 0),
        ("bit_depth", 17),
        ("bit_depth", 12.0),
    ],
)
def test_bad_model_parameters_raise(field, value):
    with pytest.raises(ValueError, match=field):
        EMCCDModel(**{field: value})


def test_model_is_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        EMCCDModel().em_gain = 10.0


@pytest.mark.parametrize("photons", [np.array([1.0, -1.0]), np.array([np.nan]), np.array([np.inf])])
@pytest.mark.parametrize(
    "call",
    [
        lambda a: gaussian_shot(a, np.random.default_rng(0)),
        lambda a: poisson_shot(a, np.random.default_rng(0)),
        lambda a: emccd_counts(a, EMCCDModel(), np.random.default_rng(0)),
        lambda a: expected_counts(a, EMCCDModel()),
        lambda a: expected_variance_counts(a, EMCCDModel()),
        max_snr,
    ],
)
def test_bad_photons_raise(call, photons):
    with pytest.raises(ValueError, match="photons_per_pixel"):
        call(photons)


def test_bad_rng_and_model_raise():
    with pytest.raises(ValueError, match="rng"):
        poisson_shot(np.ones(3), 42)
    with pytest.raises(ValueError, match="model"):
        emccd_counts(np.ones(3), {"em_gain": 300}, np.random.default_rng(0))
    with pytest.raises(ValueError, match="photons_per_pixel"):
        max_snr(np.array([]))
