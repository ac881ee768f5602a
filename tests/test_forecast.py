"""Two models told apart by their forecasts of the record (the formulation's contest)."""

import dataclasses
import importlib.util
import warnings
from pathlib import Path

import numpy as np
import pytest

import robust_sindy as rs
from robust_sindy.selection.forecast import (
    FORECAST_EVIDENCE,
    FORECAST_LEANING,
    forecast_contest,
)
from robust_sindy.simulate import rk4_batch

LORENZ = rs.systems.Lorenz()
LIBRARY = rs.PolynomialLibrary(degree=2).fit(np.zeros((1, 3)))
TRUE = LORENZ.true_coef()  # (p, n): the library's terms by the equations


def _record(seed, noise=0.01, t_end=10.0, dt=0.01):
    data = LORENZ.generate(t_end=t_end, dt=dt)
    rng = np.random.default_rng(seed)
    x = data.x + noise * data.x.std(axis=0) * rng.normal(size=data.x.shape)
    return data.t, x


def _contest(incumbent, challenger, t, x, horizon=20, **kws):
    return forecast_contest(
        LIBRARY.transform, incumbent, challenger, x, x, t, [slice(0, t.size)], horizon, **kws
    )


def _perturbed():
    # A wrong model of the kind a selection error gives: in y', the true term x z
    # swapped for a spurious y z of nearly its size.
    wrong = TRUE.copy()
    names = LIBRARY.get_feature_names(["x", "y", "z"])
    wrong[names.index("x*z"), 1] = 0.0
    wrong[names.index("y*z"), 1] = -0.8
    return wrong


@pytest.mark.parametrize("seed", range(3))
def test_the_model_that_made_the_record_wins_its_windows_from_either_side(seed):
    # 1 % noise on the states the forecasts start from and are compared with.  The true
    # model against a wrong one: far below the level when it challenges, far above it
    # when it is challenged; the windows go its way by a wide margin either way.
    t, x = _record(seed)
    wrong = _perturbed()
    take = _contest(wrong, TRUE, t, x)
    keep = _contest(TRUE, wrong, t, x)
    assert take.windows == keep.windows == (t.size - 1) // 20
    assert take.p_value < FORECAST_EVIDENCE / 1e3 and take.challenger_better
    assert keep.p_value > 0.5 and not keep.challenger_better
    assert take.wins >= 0.8 * take.windows and keep.wins <= 0.2 * keep.windows
    assert take.wins == keep.losses and take.losses == keep.wins


def test_one_model_against_itself_is_a_tie():
    t, x = _record(0)
    same = _contest(TRUE, TRUE.copy(), t, x)
    assert (same.wins, same.losses, same.p_value) == (0, 0, 1.0)
    assert not same.challenger_better


def test_units_of_states_and_time_do_not_change_the_contest():
    # States in other units (each its own factor) and time in other units: the model's
    # coefficients change with them, the windows won do not.
    t, x = _record(1)
    wrong = _perturbed()
    base = _contest(wrong, TRUE, t, x)
    a, c = np.array([1e3, 2e-2, 5.0]), 1e-2  # x -> a x, t -> c t
    powers = np.array([[LIBRARY.powers_[j].count(i) for i in range(3)] for j in range(10)])
    term = np.prod(a**powers, axis=1)  # each term's factor
    rescale = a[None, :] / (c * term[:, None])  # xi_jk -> xi_jk a_k / (c prod a^p_j)
    scaled = _contest(wrong * rescale, TRUE * rescale, c * t, x * a)
    assert (scaled.wins, scaled.losses) == (base.wins, base.losses)


def test_a_forecast_that_runs_away_loses_its_windows_and_raises_nothing():
    # A model that blows up within a window (x' = 5 x^2 added to every equation): every
    # window it reaches is lost, however far, and its overflow is not an error.
    t, x = _record(2)
    names = LIBRARY.get_feature_names(["x", "y", "z"])
    wild = TRUE.copy()
    wild[names.index("x^2"), :] += 5.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = _contest(wild, TRUE, t, x)
    assert out.wins >= 0.9 * out.windows and out.losses == 0


def test_a_library_that_refuses_some_inputs_fails_those_forecasts_only():
    # A library function outside its domain raises (as CustomLibrary does on
    # non-finite features): the rows it refuses fail, the others are forecast.
    t, x = _record(3)
    centre = x.mean(axis=0)

    def picky(z):
        if np.any(z[:, 0] > centre[0] + 3.0 * x[:, 0].std()):
            raise ValueError("outside the domain")
        return LIBRARY.transform(z)

    out = forecast_contest(picky, _perturbed(), TRUE, x, x, t, [slice(0, t.size)], 20)
    assert out.windows == (t.size - 1) // 20 and out.wins > 0


def test_windows_stay_inside_each_trajectory_and_follow_the_inputs():
    # Two trajectories stacked, and a model with an input: a window never spans the
    # join, and the forecasts read the inputs between samples.
    lib = rs.PolynomialLibrary(degree=1).fit(np.zeros((1, 2)))  # 1, x, u
    t1 = np.linspace(0.0, 5.0, 501)
    t = np.concatenate([t1, t1 + 100.0])

    def drive(s):
        return np.sin(3.0 * s)

    true = np.array([[0.0], [-1.0], [2.0]])
    x = []
    for tt in (t1, t1 + 100.0):
        u0 = drive(tt)
        x.append(rk4_batch(lambda s, u: -s + 2.0 * u, [[1.0]], tt[None], u0[None, :, None],
                           substeps=4)[0])  # fmt: skip
    x = np.vstack(x)
    u = drive(t)[:, None]
    segments = [slice(0, 501), slice(501, 1002)]
    no_input = np.array([[0.0], [-1.0], [0.0]])
    out = forecast_contest(lib.transform, no_input, true, x, x, t, segments, 25, inputs=u)
    assert out.windows == 2 * 20
    assert out.wins == out.windows  # exact model, exact records: every window


def _sensors():
    path = Path(__file__).resolve().parents[1] / "validation" / "sensors.py"
    spec = importlib.util.spec_from_file_location("sensors_script", path)
    sensors = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sensors)
    return sensors


def test_outliers_keep_the_strong_form_unless_the_weak_forms_model_forecasts_better():
    # Four competing species (LotkaVolterra4 of validation/sensors.py) at 1 % noise with
    # glitches: outliers keep the strong form below 1.5 % noise, and its derivatives,
    # carried through a nearly dependent library, select wrong terms (which ones moves
    # with the BLAS's rounding).  The weak form's model forecasts the record better in
    # most windows and is taken: the right equations, in at least 3 of 4 records, at
    # least 3 of them decisively (76 to 91 of 99 windows on this machine; under another
    # BLAS kernel one record's strong-form model is another wrong one, and the weak
    # form's wins 63 of 99, p = 0.004).
    sensors = _sensors()
    right = decisive = 0
    for seed in (201, 202, 203, 204):
        system, t, _, _, _, x = sensors.make_record("LotkaVolterra4", "glitches", "states",
                                                    seed, 3000, 0.01)  # fmt: skip
        model = rs.HuberSINDy(library=rs.PolynomialLibrary(degree=2))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rs.IdentificationWarning)
            model.fit(x, t)
        contest = model.diagnostics_.formulation_contest
        assert contest["windows"] >= 90 and contest["equations"]  # challenged, differing
        if contest["chosen"] == "weak":
            assert model.diagnostics_.formulation == "weak"
            assert contest["p_value"] <= FORECAST_EVIDENCE
            assert "forecasts the record better" in model.diagnostics_.formulation_reason
            right += np.array_equal(model.coef_.T != 0, system.coef != 0)
            decisive += bool(
                contest["wins"] >= 0.65 * contest["windows"]
                and contest["p_value"] < FORECAST_EVIDENCE / 100
            )
    assert right >= 3 and decisive >= 3


@pytest.mark.parametrize("seed", range(2))
def test_a_right_strong_form_model_is_challenged_and_stays(seed):
    # Lorenz at 0.2 % noise with 1 % of the entries spiked: outliers keep the strong
    # form, whose model is right and raises no warning; the weak form's model is fitted
    # all the same, and either selects the same terms or does not forecast better.
    data = LORENZ.generate(t_end=10.0, dt=0.01)
    rng = np.random.default_rng(seed)
    rms = np.sqrt(np.mean(data.x**2, axis=0))
    hit = rng.random(data.x.shape) < 0.01
    x = data.x + 0.002 * rms * rng.normal(size=data.x.shape)
    x = x + np.where(hit, 3.0 * data.x.std(axis=0), 0.0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = rs.HuberSINDy().fit(x, data.t)
    assert not [w for w in caught if issubclass(w.category, rs.IdentificationWarning)]
    assert model.diagnostics_.formulation == "strong" and model.weak_ is None
    contest = model.diagnostics_.formulation_contest
    reason = model.diagnostics_.formulation_reason
    if contest:
        assert contest["chosen"] == "strong" and contest["p_value"] > FORECAST_LEANING
        assert "does not forecast the record better" in reason
    else:
        assert "the weak form selects the same terms" in reason
    assert np.array_equal(model.coef_.T != 0, TRUE != 0)


@pytest.mark.skipif(importlib.util.find_spec("dysts") is None, reason="needs dysts")
def test_strong_form_models_wrong_without_a_warning_are_challenged():
    # Four records of dysts flows (draw 47, seed 13) with glitches, bursts or spikes at
    # 0.8 and 1.2 % noise, where outliers keep the strong form and its model is wrong
    # without any warning.  The weak form's model is challenged all the same: taken
    # where it forecasts better (right), else the record's lean towards it warns.
    # Asked only where the strong form's model warned, all four were silent.
    from robust_sindy import frontier, zoo
    from robust_sindy.flows import polynomial_system, simulate_system

    right = 0
    for name, family, level in [
        ("ChenLee", "glitches", 0.012), ("HyperRossler", "bursts", 0.012),
        ("IsothermalChemical", "glitches", 0.008), ("HyperRossler", "spikes", 0.008),
    ]:  # fmt: skip
        system = polynomial_system(name)
        t, x, _ = simulate_system(system, 2000, 13)
        rng = np.random.default_rng([13, 91, round(level * 1e4)])
        noisy, _ = zoo.contaminate_family(x, family, rng, zoo.Contamination(base_noise=level))
        model = rs.HuberSINDy(library=rs.PolynomialLibrary(degree=4))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            model.fit(noisy, t)
        assert model.diagnostics_.formulation_contest["equations"]  # challenged, differing
        exact = np.array_equal(model.coef_.T != 0, frontier._truth(system, x.shape[1]) != 0)
        assert exact or caught, f"{name} {family} {level}: wrong without a warning"
        right += exact
    assert right >= 1


def test_a_record_that_leans_to_the_weak_forms_model_warns():
    # The contest's record, short of the level that takes the weak form's model: a
    # warning where the windows lean towards it at the 5 % level, none where they do
    # not, none where it was taken.
    data = LORENZ.generate(t_end=5.0)
    d = rs.HuberSINDy().fit(data.x, data.t, x_dot=data.x_dot).diagnostics_
    assert d.findings() == []
    contest = dict(horizon=30, windows=66, wins=42, losses=24, p_value=0.018,
                   equations="x2'", chosen="strong")  # fmt: skip
    ((kind, message),) = dataclasses.replace(d, formulation_contest=contest).findings()
    assert kind == "formulations disagree"
    assert "x2'" in message and "42 of 66" in message and "formulation='weak'" in message
    for change in (dict(p_value=0.2, wins=36, losses=30), dict(chosen="weak", p_value=1e-6)):
        quiet = dataclasses.replace(d, formulation_contest={**contest, **change})
        assert quiet.findings() == []


def test_rk4_batch_takes_more_steps_across_a_gap():
    # x' = -x on times with one interval 40 times the others: with as many steps per
    # column as its longest interval needs, every sample is within 1e-8 of exp(-t) (two
    # steps across the gap would be 4e-3 off).
    t = np.concatenate([np.arange(0.0, 0.5, 0.05), [2.5], 2.5 + np.arange(1, 6) * 0.05])
    grid = np.vstack([t, t + 1.0])
    counts = 2 * np.ceil(np.diff(t) / np.median(np.diff(t))).astype(int)
    x = rk4_batch(lambda x, u: -x, np.ones((2, 1)), grid, substeps=counts)
    assert np.allclose(x[:, :, 0], np.exp(-(grid - grid[:, :1])), rtol=0, atol=1e-8)
