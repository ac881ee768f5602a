"""The zoo: dysts' polynomial flows, their true coefficients, one case, the quick command."""

import numpy as np
import pytest

from robust_sindy import zoo
from robust_sindy.cli import main
from robust_sindy.flows import lorenz96_records, polynomial_system


@pytest.fixture(scope="module")
def lorenz():
    return polynomial_system("Lorenz")


def test_the_polynomial_flows_are_found_with_their_coefficients():
    systems = {s.name: s for s in zoo.polynomial_systems()}
    assert len(systems) >= 70
    lorenz = systems["Lorenz"]
    assert lorenz.degree == 2 and lorenz.n_states == 3
    # dysts' Lorenz: sigma 10, rho 28, beta 2.667 on (1, x, y, z, x^2, ..., z^2).
    assert np.isclose(lorenz.coef[1, 0], -10) and np.isclose(lorenz.coef[2, 0], 10)
    assert np.isclose(lorenz.coef[1, 1], 28) and np.isclose(lorenz.coef[6, 1], -1)
    assert np.isclose(lorenz.coef[3, 2], -2.667) and np.isclose(lorenz.coef[5, 2], 1)
    assert np.count_nonzero(lorenz.coef) == 7


def test_a_flow_asked_for_alone_is_the_flow_of_the_whole_list(monkeypatch):
    from robust_sindy import flows

    every = flows.polynomial_systems()
    # Evaluated again from scratch: only the flows asked for, on their own points.
    monkeypatch.setattr(flows, "_FOUND", {})
    monkeypatch.setattr(flows, "_SCANS", {})
    picked = {"HyperRossler", "Lorenz", every[-1].name}
    alone = flows.polynomial_systems(names=sorted(picked))
    assert [s.name for s in alone] == [s.name for s in every if s.name in picked]
    assert set(flows._FOUND) == {(4, 3, name) for name in picked}
    assert [s.name for s in flows.polynomial_systems(first=4)] == [s.name for s in every[:4]]
    for system in [*alone, *flows.polynomial_systems(first=4)]:
        full = next(s for s in every if s.name == system.name)
        assert system is not full and system.powers == full.powers
        np.testing.assert_array_equal(system.coef, full.coef)
        np.testing.assert_array_equal(system.ic, full.ic)
        assert system.dt == full.dt and system.degree == full.degree
    for name in ("DoublePendulum", "NoSuchFlow"):  # not polynomial; not in dysts
        with pytest.raises(ValueError, match=f"name: '{name}' is not a dysts flow"):
            flows.polynomial_system(name)


@pytest.mark.parametrize("family", zoo.ALL_FAMILIES)
def test_contamination_families_mark_what_they_change(family):
    rng = np.random.default_rng(0)
    x = np.cumsum(rng.normal(size=(500, 3)), axis=0)
    noisy, bad = zoo.contaminate_family(x, family, rng)
    assert noisy.shape == x.shape
    big = np.abs(noisy - x) > 0.05 * x.std(axis=0)
    assert not (big & ~bad).any() or family == "heavy"
    assert bad.any() == (family not in ("clean", "heavy", *zoo.TIME_FAMILIES))
    assert np.array_equal(np.isnan(noisy), bad if family == "missing" else np.zeros_like(bad))


@pytest.mark.parametrize("family", zoo.TIME_FAMILIES)
def test_time_families_give_increasing_times_over_the_span(family):
    for seed in range(3):
        t = zoo.sample_times(family, 2000, 0.01, np.random.default_rng(seed))
        steps = np.diff(t)
        assert t.size == 2000 and t[0] == 0 and (steps > 0).all()
        if family == "gaps":  # three gaps of 100 steps, the rest on the grid
            assert np.sum(steps > 1.5 * 0.01) == 3
            assert np.allclose(steps[steps > 0.015], 0.01 * 101)
        elif family == "jitter":
            assert np.abs(t - 0.01 * np.arange(2000) - (t[0] - 0)).max() < 0.01
        else:
            assert abs(t[-1] - 0.01 * 1999) < 0.1
    assert zoo.sample_times("clean", 2000, 0.01, np.random.default_rng(0)) is None


def test_huber_sindy_identifies_a_zoo_case_exactly(lorenz):
    rows = zoo.run_case(lorenz, "spikes", "exact", 0, methods=("huber",), n_samples=800)
    assert rows[0]["exact"] and rows[0]["iae"] < 0.05


def test_zoo_quick_command_writes_its_report(tmp_path):
    assert main(["zoo", "--quick", "--out", str(tmp_path), "--quiet", "--jobs", "1"]) == 0
    text = (tmp_path / "zoo.md").read_text()
    assert "| clean | exact |" in text
    assert (tmp_path / "zoo.png").stat().st_size > 0
    assert len((tmp_path / "zoo.csv").read_text().splitlines()) == 1 + 2 * 2 * 2 * 4


def test_the_ensemble_peer_gives_the_same_result_on_every_run(lorenz):
    # PySINDy's bagging draws from NumPy's global random state; the zoo seeds it per case
    # and restores it afterwards.
    np.random.seed(123)  # noqa: NPY002 (the legacy state PySINDy draws from)
    before = np.random.random()  # noqa: NPY002 (the legacy state PySINDy draws from)
    np.random.seed(123)  # noqa: NPY002 (the legacy state PySINDy draws from)
    runs = [
        zoo.run_case(lorenz, "rows", "states", 0, methods=("ensemble",), n_samples=600)
        for _ in range(2)
    ]
    assert runs[0][0]["iae"] == runs[1][0]["iae"]
    assert runs[0][0]["n_found"] == runs[1][0]["n_found"]
    assert np.random.random() == before  # the caller's random state is left alone  # noqa: NPY002 (the legacy state PySINDy draws from)


def test_a_case_can_take_other_contamination(lorenz):
    fewer_rows = zoo.Contamination(rows_fraction=0.1)
    (row,) = zoo.run_case(
        lorenz, "rows", "exact", 0, methods=("huber",), n_samples=600,
        contamination=fewer_rows,
    )  # fmt: skip
    assert row["contaminated"] == 0.1
    (row,) = zoo.run_case(lorenz, "rows", "exact", 0, methods=("huber",), n_samples=600)
    assert row["contaminated"] == zoo.ZOO_CONTAMINATION.rows_fraction == 0.2


def test_zoo_families_option_is_checked(capsys):
    with pytest.raises(SystemExit):
        main(["zoo", "--families", "clean,foo"])
    assert "unknown families ['foo']" in capsys.readouterr().err


def test_lorenz96_records_follow_the_systems_coefficients():
    # The direct right-hand side of the records and the zoo system's coefficients on
    # the degree-2 monomials are the same equations.
    t, x, x_dot, system = lorenz96_records(7, 300, seed=2)
    assert x.shape == x_dot.shape == (300, 7) and np.all(np.diff(t) > 0)
    np.testing.assert_allclose(x_dot, system.rhs(x), rtol=1e-12, atol=1e-11)
    assert x.std(axis=0).min() > 1.0  # on the attractor, not at the fixed point


def test_the_scaling_run_times_and_checks_each_method():
    rows = zoo.run_scaling(((5, 1500),), families=("clean",), methods=("huber", "stlsq"),
                           memory=True, progress=False)  # fmt: skip
    huber, stlsq = rows
    assert huber.method == "HuberSINDy()" and stlsq.method == "PySINDy STLSQ"
    assert huber.exact is True and huber.seconds > 0 and huber.peak_mb > 0
    assert huber.ratio == pytest.approx(huber.seconds / stlsq.seconds)
    assert huber.true == 5 * 4 and huber.terms == 21
    text = zoo.scaling_table(rows)
    assert "| 5 (21) | 1500 | clean | " in text and "exact" in text


def test_a_scaling_size_may_give_its_sampling_step(monkeypatch):
    # states:samples:step: the record sampled that far apart, and the table says so.
    given = []

    def spy(method, system, t, x, x_dot, seed=0):
        given.append(t.copy())
        return system.coef.copy(), []

    monkeypatch.setattr(zoo, "_fit_method", spy)
    rows = zoo.run_scaling(((5, 300, 0.05), (5, 300)), families=("clean",),
                           methods=("stlsq",), progress=False)  # fmt: skip
    np.testing.assert_allclose(np.diff(given[0]), 0.05, rtol=1e-9)
    np.testing.assert_allclose(np.diff(given[1]), 0.01, rtol=1e-9)
    assert [r.step for r in rows] == [0.05, 0.01]
    text = zoo.scaling_table(rows)
    assert "| 5 (21) | 300 (step 0.05) | clean | " in text and "| 5 (21) | 300 | clean | " in text


def test_the_scaling_run_from_noisy_states_gives_both_methods_the_states_alone(monkeypatch):
    given = []
    fit_method = zoo._fit_method

    def spy(method, system, t, x, x_dot, seed=0):
        given.append((method, x_dot, x.copy()))
        return fit_method(method, system, t, x, x_dot, seed)

    monkeypatch.setattr(zoo, "_fit_method", spy)
    rows = zoo.run_scaling(((5, 1500),), families=("clean",), progress=False,
                           derivatives="states", noise=0.02)  # fmt: skip
    assert [r.method for r in rows] == ["HuberSINDy()", "PySINDy STLSQ"]
    assert all(r.exact is not None and r.seconds > 0 for r in rows)
    assert [m for m, _, _ in given] == ["huber", "stlsq"] and all(d is None for _, d, _ in given)
    _, x, _, _ = lorenz96_records(5, 1500, 0)
    added = given[0][2] - x  # the noise (and the zoo's base noise of the clean family)
    np.testing.assert_allclose(added.std(axis=0) / x.std(axis=0), 0.02, rtol=0.1)
    with pytest.raises(ValueError, match="derivatives"):
        zoo.run_scaling(((5, 1500),), derivatives="measured", progress=False)
    with pytest.raises(ValueError, match="noise"):
        zoo.run_scaling(((5, 1500),), noise=-0.1, progress=False)


def test_the_sensor_scripts_rings_have_the_coefficients_of_their_equations():
    # validation/sensors.py's LorenzRing_N is scored against its coefficients on the
    # degree-2 monomials: they must give the ring's equations (each Lorenz system driven
    # through its first state by the next one's) at any state.
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "validation" / "sensors.py"
    spec = importlib.util.spec_from_file_location("sensors_script", path)
    sensors = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sensors)
    system = sensors._system("LorenzRing_3")
    v = np.random.default_rng(0).normal(scale=10.0, size=(50, 9))
    x, y, z = v[:, 0::3], v[:, 1::3], v[:, 2::3]
    expected = np.empty_like(v)
    expected[:, 0::3] = 10.0 * (y - x) + 0.5 * (np.roll(x, -1, axis=1) - x)
    expected[:, 1::3] = x * (28.0 - z) - y
    expected[:, 2::3] = x * y - 8.0 / 3.0 * z
    assert np.allclose(system.library(v) @ system.coef, expected, rtol=1e-12, atol=1e-9)
    assert int((system.coef != 0).sum()) == 8 * 3  # three terms in x', three in y', two in z'
    with pytest.raises(ValueError, match="LorenzRing_N needs N of at least 2"):
        sensors._system("LorenzRing_1")
    # VanDerPolRing_N: detuned Van der Pol oscillators, each pulled by the next one's
    # position, on the cubic monomials.
    system = sensors._system("VanDerPolRing_4")
    v = np.random.default_rng(1).normal(scale=2.0, size=(50, 8))
    x, y = v[:, 0::2], v[:, 1::2]
    w = 1.0 + 0.23 * np.arange(4)
    expected = np.empty_like(v)
    expected[:, 0::2] = y
    expected[:, 1::2] = (1 - x**2) * y - w**2 * x + 0.3 * (np.roll(x, -1, axis=1) - x)
    assert np.allclose(system.library(v) @ system.coef, expected, rtol=1e-12, atol=1e-9)
    assert int((system.coef != 0).sum()) == 5 * 4  # one term in x', four in y'
    with pytest.raises(ValueError, match="VanDerPolRing_N needs N of at least 2"):
        sensors._system("VanDerPolRing_1")
    # RosslerRing_N: Rössler systems, each driven through its x by the next one's.
    system = sensors._system("RosslerRing_3")
    v = np.random.default_rng(2).normal(scale=5.0, size=(50, 9))
    x, y, z = v[:, 0::3], v[:, 1::3], v[:, 2::3]
    expected = np.empty_like(v)
    expected[:, 0::3] = -y - z + 0.1 * (np.roll(x, -1, axis=1) - x)
    expected[:, 1::3] = x + 0.2 * y
    expected[:, 2::3] = 0.2 + z * (x - 5.7)
    assert np.allclose(system.library(v) @ system.coef, expected, rtol=1e-12, atol=1e-9)
    assert int((system.coef != 0).sum()) == 9 * 3  # four terms in x', two in y', three in z'
    # LotkaVolterra4: x_i' = r_i x_i (1 - sum_j a_ij x_j).
    system = sensors._system("LotkaVolterra4")
    v = np.random.default_rng(3).uniform(0.1, 0.8, size=(50, 4))
    r = np.array([1.0, 0.72, 1.53, 1.27])
    a = [[1, 1.09, 1.52, 0], [0, 1, 0.44, 1.36], [2.33, 0, 1, 0.47], [1.21, 0.51, 0.35, 1]]
    a = np.array(a)
    expected = r * v * (1 - v @ a.T)
    assert np.allclose(system.library(v) @ system.coef, expected, rtol=1e-12, atol=1e-12)


def test_the_flows_monomials_are_the_polynomial_librarys_columns():
    # The zoo's and the sensor script's right-hand sides are scored against
    # PolynomialLibrary's columns: the same monomials in the same order, each the
    # product of its factors from the left (exactly so, shorter ones included).
    import robust_sindy as rs
    from robust_sindy.flows import monomial_factors, monomial_powers, monomials

    x = np.random.default_rng(4).normal(size=(40, 3))
    powers = monomial_powers(3, 3)
    got = monomials(x, monomial_factors(powers, 3))
    assert got.shape == (40, 20)
    np.testing.assert_allclose(got, rs.PolynomialLibrary(degree=3).fit(x).transform(x),
                               rtol=1e-13)  # fmt: skip
    for j, combo in enumerate(powers):
        column = np.ones(40)
        for i in combo:
            column = column * x[:, i]
        assert np.array_equal(got[:, j], column), combo
