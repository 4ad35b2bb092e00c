"""Per aid source status (companion.nav.aid_status) and the divergence monitor
(companion.nav.integrity) on synthetic innovation sequences with known statistics."""
import numpy as np
from scipy.stats import chi2

from companion.nav.aid_status import AidSourceBook
from companion.nav.filter import UpdateReport
from companion.nav.integrity import IntegrityLimits, IntegrityMonitor, IntegrityState

GATE = float(chi2.ppf(0.999, 1))


def _report(kind, z, S):
    ratio = z * z / (S * GATE)
    return UpdateReport(kind, [f"G{i:02d}" for i in range(len(z))], z, S, ratio, ratio <= 1.0)


def _run(mon, book, rng, epochs, t0=0.0, bias_sigma=0.0, rows=7):
    states = []
    for k in range(epochs):
        t = t0 + k
        for kind in ("pseudorange", "tdcp"):
            S = np.full(rows, 4.0)
            z = rng.normal(0.0, 2.0, rows) + bias_sigma * 2.0
            book.record(_report(kind, z, S), t, GATE)
        mon.evaluate(book, t)
        states.append(mon.state)
    return states


def test_consistent_innovations_never_raise_an_alarm():
    book, mon = AidSourceBook(5.0), IntegrityMonitor(IntegrityLimits())
    states = _run(mon, book, np.random.default_rng(0), 3000)
    assert set(states) == {IntegrityState.OK}
    w = book.window("pseudorange")
    assert w.n_updates == 6 and w.n_rows == 42 and 0.4 < w.nis_accepted_mean < 2.0
    st = book.sources["tdcp"]
    assert st.fused and st.t_last_fused == 2999 and st.updates == 3000 and len(st.test_ratio) == 7


def test_inconsistent_innovations_suspect_at_once_then_diverged_within_the_window():
    book, mon = AidSourceBook(5.0), IntegrityMonitor(IntegrityLimits(), counters={})
    rng = np.random.default_rng(1)
    _run(mon, book, rng, 20)
    # a filter 2.5 sigma off on every row: few rows rejected by the gate, NIS ~7 per row
    states = _run(mon, book, rng, 10, t0=20.0, bias_sigma=2.5)
    assert states[0] == IntegrityState.SUSPECT                 # the first epoch: nothing injected
    k = states.index(IntegrityState.DIVERGED)
    assert 1 <= k <= 5
    assert mon.counters["integrity.diverged"] == 1 and "NIS" in mon.reason


def test_one_bad_epoch_is_a_pause_not_a_divergence():
    book, mon = AidSourceBook(5.0), IntegrityMonitor(IntegrityLimits(), counters={})
    rng = np.random.default_rng(2)
    _run(mon, book, rng, 20)
    s = _run(mon, book, rng, 1, t0=20.0, bias_sigma=6.0)         # one epoch of outliers
    s += _run(mon, book, rng, 10, t0=21.0)
    assert s[0] == IntegrityState.SUSPECT and IntegrityState.DIVERGED not in s
    assert s[1] == IntegrityState.SUSPECT and s[2] == IntegrityState.OK    # two clean epochs


def test_probation_lasts_one_full_consistent_window():
    book, mon = AidSourceBook(5.0), IntegrityMonitor(IntegrityLimits(), counters={})
    mon.restart(100.0, probation=True)
    states = _run(mon, book, np.random.default_rng(3), 10, t0=100.0)
    assert states[:5] == [IntegrityState.PROBATION] * 5 and states[5] == IntegrityState.OK
    assert mon.counters["integrity.probation_passed"] == 1
