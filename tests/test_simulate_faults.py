"""Sensor faults on request (``Fault``, ``inject_faults``, ``kckf simulate --fault``): each
kind changes exactly its column and span, the truth never, and the record survives meta.json."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from kckf_jax import Fault, Robot, inject_faults, read_session, simulate, write_session
from kckf_jax.cli import main

ROBOT = Robot.from_spec("x,y,x,y")
DEG = np.pi / 180.0
ADC_STEP = 3.3 / 4096  # the simulator's 12-bit ADC
LSB = 8.75e-3 * DEG  # the simulator's gyro step (+-250 dps)


def _clean():
    # 10 s, 2 % of the readings missing: a missing reading must stay missing under a fault.
    return simulate(ROBOT, "cyclic", seed=3, duration_s=10.0, drop_prob=0.02)


@pytest.fixture(scope="module")
def clean():
    return _clean()


def _col(session, column):
    names = session.robot.hall_names + session.robot.gyro_names
    assert column in names
    if column in session.robot.hall_names:
        return session.hall_v[:, session.robot.hall_names.index(column)]
    return session.gyro[:, session.robot.gyro_names.index(column)]


def _only_changed(clean, bad, columns):
    """Every column but ``columns`` is identical (NaN included), the truth too, and ``clean``'s
    arrays were not touched."""
    fresh = _clean()
    for name in clean.robot.hall_names + clean.robot.gyro_names:
        np.testing.assert_array_equal(_col(clean, name), _col(fresh, name))
        if name not in columns:
            np.testing.assert_array_equal(_col(bad, name), _col(clean, name), err_msg=name)
    np.testing.assert_array_equal(bad.t, clean.t)
    np.testing.assert_array_equal(bad.mocap, clean.mocap)
    np.testing.assert_array_equal(bad.mocap_t, clean.mocap_t)
    assert bad.mocap_time_offset_s == clean.mocap_time_offset_s
    assert "simulated_faults" not in clean.extra_meta


def _span(clean, a, b):
    rows = (clean.t >= a) & (clean.t <= b)
    assert 99 <= rows.sum() <= 101 * (b - a)  # a row every 10 ms, jittered by 0.5 ms
    return rows


def _one(clean, text, seed=0):
    bad = inject_faults(clean, [Fault.parse(text)], seed=seed)
    (record,) = bad.extra_meta["simulated_faults"]
    return bad, record


# ------------------------------------------------------------------------------- the text form
@pytest.mark.parametrize("text, fields, canonical", [
    ("disconnect:hall1_x_l@20-30", ("disconnect", "hall1_x_l", 20.0, 30.0, None), None),
    ("noise:hall2_y_r@10-12=0.5", ("noise", "hall2_y_r", 10.0, 12.0, 0.5), None),
    ("clip:gyro2_x=2.0", ("clip", "gyro2_x", None, None, 2.0), "clip:gyro2_x=2"),
    ("bias_step:gyro3_x@30=0.2", ("bias_step", "gyro3_x", 30.0, None, 0.2), None),
    ("bias_step:gyro3_x@30-=0.2", ("bias_step", "gyro3_x", 30.0, None, 0.2),
     "bias_step:gyro3_x@30=0.2"),
    ("dropout:gyro1_y@-5", ("dropout", "gyro1_y", None, 5.0, None), None),
    ("coeff:hall1_x_l=10", ("coeff", "hall1_x_l", None, None, 10.0), None),
    ("swap:hall1_x", ("swap", "hall1_x", None, None, None), None),
    ("gap@120-720", ("gap", None, 120.0, 720.0, None), None),
    ("blank:gyro4_x=1.2", ("blank", "gyro4_x", None, None, 1.2), None),
    ("stuck:gyro1_x@1.5e1-20.25=-0.25", ("stuck", "gyro1_x", 15.0, 20.25, -0.25),
     "stuck:gyro1_x@15-20.25=-0.25"),
    ("  sign:gyro5_z ", ("sign", "gyro5_z", None, None, None), "sign:gyro5_z"),
    ("flicker:hall4_y_r@.5-1e-3=1e-05", None, None),  # from > to: checked below
])
def test_parse_round_trips(text, fields, canonical):
    if fields is None:
        with pytest.raises(ValueError, match="after its end"):
            Fault.parse(text)
        return
    f = Fault.parse(text)
    assert (f.kind, f.column, f.from_s, f.to_s, f.size) == fields
    assert str(f) == (canonical or text)
    assert Fault.parse(str(f)) == f
    doc = json.loads(json.dumps(f.to_json()))
    assert doc == dict(zip(("kind", "column", "from_s", "to_s", "size"), fields))
    assert Fault.from_json(doc) == f
    assert Fault(*fields) == f


def test_numbers_round_trip_exactly():
    f = Fault("noise", "gyro1_x", 0.1 + 0.2, 1 / 3, 1e-5)
    assert str(f) == "noise:gyro1_x@0.30000000000000004-0.3333333333333333=1e-05"
    assert Fault.parse(str(f)) == f
    assert Fault("bias_step", "gyro1_x", 3, None, 1).from_s == 3.0  # ints become floats


@pytest.mark.parametrize("text, message", [
    ("", "expected KIND:COLUMN[@FROM-TO][=SIZE] or gap@FROM-TO"),
    ("noise:gyro1_x@1-2=0.5=3", "size '0.5=3' is not a finite number"),
    ("nonsense:gyro1_x", "unknown kind 'nonsense'; expected one of disconnect, short, noise"),
    ("Noise:gyro1_x", "unknown kind 'Noise'"),
    ("noise", "noise needs a column (a Hall column like hall1_x_l or a gyro column like "
              "gyro2_x); expected noise:COLUMN"),
    ("noise:", "noise needs a column"),
    ("noise:gyro9", "column 'gyro9' is not a sensor column"),
    ("noise:hall1_x", "noise does not apply to the joint axis 'hall1_x'"),
    ("clip:hall1_x_l", "clip does not apply to the Hall column 'hall1_x_l'; expected a gyro "
                       "column"),
    ("disconnect:gyro1_x", "disconnect does not apply to the gyro column 'gyro1_x'"),
    ("swap:hall1_x_l", "swap does not apply to the Hall column 'hall1_x_l'; expected a joint "
                       "axis"),
    ("gap:gyro1_x@1-2", "a gap takes no column (got 'gyro1_x')"),
    ("gap:@1-2", "a gap takes no column (got '')"),
    ("gap", "a gap needs both ends of its span"),
    ("gap@5", "a gap needs both ends of its span"),
    ("noise:gyro1_x@30-20", "the span starts at 30 s, after its end 20 s"),
    ("noise:gyro1_x@a-b", "span 'a-b' is not FROM-TO"),
    ("noise:gyro1_x@", "span '' is not FROM-TO"),
    ("noise:gyro1_x@-", "span '-' is not FROM-TO"),
    ("noise:gyro1_x@1020", None),  # a valid span: from 1020 s to the end
    ("noise:gyro1_x@10 20", "span '10 20' is not FROM-TO"),
    ("noise:gyro1_x@10_20", "span '10_20' is not FROM-TO"),
    ("noise:gyro1_x=abc", "size 'abc' is not a finite number"),
    ("noise:gyro1_x=nan", "size 'nan' is not a finite number"),
    ("noise:gyro1_x=inf", "size 'inf' is not a finite number"),
    ("noise:hall1_x_l=-0.5", "size -0.5 is negative; expected a standard deviation >= 0"),
    ("disconnect:hall1_x_l=-1", "size -1 is negative"),
    ("flicker:hall1_x_l=1.5", "size 1.5 is not a probability"),
    ("clip:gyro1_x=0", "size 0 is not positive"),
    ("blank:gyro1_x=-1.2", "size -1.2 is negative"),
    ("coeff:hall1_x_l=0", "size 0 is not positive"),
    ("coeff:hall1_x_l@1-2", "coeff takes no span (it holds for the whole session); expected "
                            "coeff:COLUMN[=SIZE]"),
    ("sign:gyro1_x@1-2", "sign takes no span (it holds for the whole session); expected "
                         "sign:COLUMN"),
    ("dropout:gyro1_x=1", "dropout takes no size (got 1)"),
    ("swap:hall1_x=1", "swap takes no size"),
    ("gap@1-2=3", "gap takes no size"),
])
def test_parse_errors_are_one_line_naming_the_text(text, message):
    if message is None:
        assert Fault.parse(text).from_s == 1020.0
        return
    with pytest.raises(ValueError) as info:
        Fault.parse(text)
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith(f"fault {text.strip()!r}: "), msg
    assert message in msg, msg


@pytest.mark.parametrize("kwargs, message", [
    ({"kind": "noise", "column": "gyro1_x", "from_s": float("inf")},
     "from_s must be a finite number, got inf"),
    ({"kind": "noise", "column": "gyro1_x", "size": True}, "size must be a finite number"),
    ({"kind": "gap", "column": None, "from_s": 3.0, "to_s": 1.0},
     "fault 'gap@3-1': the span starts at 3 s, after its end 1 s"),
    ({"kind": "sign", "column": "gyro1_x", "size": -1.0}, "sign takes no size"),
])
def test_constructor_checks_like_parse(kwargs, message):
    with pytest.raises(ValueError, match="^fault ") as info:
        Fault(**kwargs)
    assert message in str(info.value)


@pytest.mark.parametrize("doc, message", [
    ({"kind": "noise", "column": "gyro1_x", "sise": 1.0}, "unknown key 'sise'"),
    ({"column": "gyro1_x"}, "'kind' must be one of disconnect"),
    ({"kind": "noise", "column": 3}, "'column' must be a column name or null, got 3"),
    ({"kind": "noise", "column": "gyro1_x", "to_s": "3"}, "'to_s' must be a number or null"),
    ({"kind": "noise", "column": "gyro1_x", "size": False}, "'size' must be a number or null"),
    (["noise"], "expected a JSON object, got list"),
    ({"kind": "noise", "column": "gyro1_x", "size": -1}, "size -1 is negative"),
])
def test_from_json_errors(doc, message):
    with pytest.raises(ValueError) as info:
        Fault.from_json(doc)
    assert message in str(info.value)


# ------------------------------------------------------------------------------- the session
@pytest.mark.parametrize("text, message", [
    ("noise:hall5_x_l", "column 'hall5_x_l' is not on this robot (joints x,y,x,y: Hall "
                        "hall1_x_l..hall4_y_r, gyro gyro1_x..gyro5_z)"),
    ("dropout:gyro6_x", "column 'gyro6_x' is not on this robot"),
    ("swap:hall1_y", "column 'hall1_y' is not on this robot"),
    ("noise:gyro1_x@5-50", "the span 5-50 s is outside the session (0-10 s)"),
    ("noise:gyro1_x@20", "the span 20-9.990218 s is outside the session"),
    ("noise:gyro1_x@5.001-5.002", "the span 5.001-5.002 s holds no sensor row (a row every "
                                  "0.01 s)"),
    ("gap@0-2", "a gap must leave sensor rows before and after it"),
    ("gap@9-10", "a gap must leave sensor rows before and after it"),
    ("disconnect:hall1_x_l=3.5", "3.5 V is outside the ADC's range; expected 0-3.3 V"),
    ("stuck:hall1_x_l=4", "4 V is outside the ADC's range"),
    ("stuck:gyro1_x=-100", "-100 rad/s is beyond the gyro's range; expected at most 69.81"),
])
def test_session_errors(clean, text, message):
    with pytest.raises(ValueError) as info:
        inject_faults(clean, [Fault.parse("dropout:gyro1_x@1-2"), Fault.parse(text)])
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"fault {text!r}: "), msg
    assert message in msg, msg


def test_a_span_may_run_to_the_end_of_the_last_sample(clean):
    # --duration 10 gives rows up to 9.99 s; "@5-10" names the session's own length.
    bad, record = _one(clean, "dropout:gyro1_x@5-10")
    assert (record["from_s"], record["to_s"]) == (5.0, 10.0)
    assert np.isnan(_col(bad, "gyro1_x")[clean.t >= 5]).all()


def test_disconnect_and_short_read_the_rails(clean):
    rows = _span(clean, 2, 3)
    for text, value in (("disconnect:hall1_x_l@2-3", 0.0), ("short:hall1_x_l@2-3", 3.3),
                        ("disconnect:hall1_x_l@2-3=1.65", 1.65)):
        bad, record = _one(clean, text)
        _only_changed(clean, bad, ["hall1_x_l"])
        before, after = _col(clean, "hall1_x_l"), _col(bad, "hall1_x_l")
        np.testing.assert_array_equal(after[~rows], before[~rows])
        present = rows & np.isfinite(before)
        assert (after[present] == value).all() and present.sum() >= 95
        assert np.isnan(after[rows & np.isnan(before)]).all()  # a lost reading stays lost
        assert record == {"kind": text.split(":")[0], "column": "hall1_x_l", "from_s": 2.0,
                          "to_s": 3.0, "size": value}


@pytest.mark.parametrize("column, size, step, top", [
    ("hall2_y_r", 0.5, ADC_STEP, 3.3), ("gyro2_x", 1.0, LSB, 250 * DEG)])
def test_noise_has_its_size_and_the_converters_grid(clean, column, size, step, top):
    rows = _span(clean, 2, 8)
    bad, record = _one(clean, f"noise:{column}@2-8", seed=5)
    _only_changed(clean, bad, [column])
    before, after = _col(clean, column), _col(bad, column)
    np.testing.assert_array_equal(after[~rows], before[~rows])
    ok = rows & np.isfinite(before)
    np.testing.assert_array_equal(np.isnan(after), np.isnan(before))
    diff = after[ok] - before[ok]
    assert 0.9 * size < np.std(diff) < 1.1 * size and abs(np.mean(diff)) < 0.15 * size
    np.testing.assert_allclose(after[ok] / step, np.round(after[ok] / step), atol=1e-6)
    assert np.abs(after[ok]).max() <= top
    assert record["size"] == size
    # Seeded: the same seed draws the same noise, another seed other noise.
    again = inject_faults(clean, [Fault.parse(f"noise:{column}@2-8")], seed=5)
    other = inject_faults(clean, [Fault.parse(f"noise:{column}@2-8")], seed=6)
    np.testing.assert_array_equal(_col(again, column), after)
    assert not np.array_equal(_col(other, column)[ok], after[ok])


def test_stuck_holds_the_reading_at_from_or_the_size(clean):
    rows = _span(clean, 4, 6)
    before = _col(clean, "hall3_x_l")
    first = int(np.argmax(rows))
    held = before[first] if np.isfinite(before[first]) else before[first - 1]
    bad, record = _one(clean, "stuck:hall3_x_l@4-6")
    _only_changed(clean, bad, ["hall3_x_l"])
    after = _col(bad, "hall3_x_l")
    ok = rows & np.isfinite(before)
    assert np.isfinite(held) and (after[ok] == held).all()
    assert np.ptp(before[ok]) > 0.05  # it did move there
    np.testing.assert_array_equal(after[~rows], before[~rows])
    assert record["size"] == float(held) and record["to_s"] == 6.0
    bad, record = _one(clean, "stuck:gyro1_y@4=-0.25")
    g = _col(bad, "gyro1_y")
    late = clean.t >= 4
    assert (g[late & np.isfinite(_col(clean, "gyro1_y"))] == -0.25).all()
    assert record["to_s"] == float(clean.t[-1]) and record["size"] == -0.25


def test_flicker_drops_to_zero_volts_with_its_probability(clean):
    rows = _span(clean, 1, 9)
    bad, record = _one(clean, "flicker:hall4_y_r@1-9", seed=2)
    _only_changed(clean, bad, ["hall4_y_r"])
    before, after = _col(clean, "hall4_y_r"), _col(bad, "hall4_y_r")
    ok = rows & np.isfinite(before)
    zero = ok & (after == 0.0)
    assert 0.24 < zero.sum() / ok.sum() < 0.36 and record["size"] == 0.3
    np.testing.assert_array_equal(after[ok & ~zero], before[ok & ~zero])
    np.testing.assert_array_equal(after[~rows], before[~rows])
    assert (before[ok] > 0.5).all()  # a zero can only come from the fault


def test_clip_saturates_the_whole_session(clean):
    before = _col(clean, "gyro4_x")
    bad, record = _one(clean, "clip:gyro4_x")  # default 2.0 rad/s
    _only_changed(clean, bad, ["gyro4_x"])
    after = _col(bad, "gyro4_x")
    np.testing.assert_array_equal(after, np.clip(before, -2.0, 2.0))
    assert (np.abs(np.nan_to_num(before)) > 2.0).sum() == 52 and np.nanmax(np.abs(after)) == 2.0
    assert record == {"kind": "clip", "column": "gyro4_x", "from_s": 0.0,
                      "to_s": float(clean.t[-1]), "size": 2.0}


def test_bias_step_from_its_start_to_the_end(clean):
    before = _col(clean, "gyro3_x")
    bad, record = _one(clean, "bias_step:gyro3_x@4")
    _only_changed(clean, bad, ["gyro3_x"])
    after = _col(bad, "gyro3_x")
    late = clean.t >= 4
    np.testing.assert_array_equal(after[~late], before[~late])
    ok = late & np.isfinite(before)
    np.testing.assert_allclose(after[ok] - before[ok], 0.2, atol=LSB / 2 + 1e-12)
    np.testing.assert_allclose(after[ok] / LSB, np.round(after[ok] / LSB), atol=1e-6)
    assert np.isnan(after[late & np.isnan(before)]).all()
    assert (record["from_s"], record["size"]) == (4.0, 0.2)


def test_blank_makes_the_fast_readings_missing(clean):
    before = _col(clean, "gyro4_x")
    bad, record = _one(clean, "blank:gyro4_x")  # default 1.2 rad/s
    _only_changed(clean, bad, ["gyro4_x"])
    after = _col(bad, "gyro4_x")
    fast = np.abs(np.nan_to_num(before)) >= 1.2
    assert fast.sum() == 290 and np.isnan(after[fast]).all()
    np.testing.assert_array_equal(after[~fast], before[~fast])
    assert record["size"] == 1.2


@pytest.mark.parametrize("column", ["hall2_y_l", "gyro5_y"])
def test_dropout_makes_the_span_missing(clean, column):
    rows = _span(clean, 3, 4)
    bad, record = _one(clean, f"dropout:{column}@3-4")
    _only_changed(clean, bad, [column])
    assert np.isnan(_col(bad, column)[rows]).all()
    np.testing.assert_array_equal(_col(bad, column)[~rows], _col(clean, column)[~rows])
    assert record["size"] is None


def test_coeff_changes_only_the_calibration(clean):
    bad, record = _one(clean, "coeff:hall1_x_l")
    _only_changed(clean, bad, [])
    assert bad.hall_models["hall1_x_l"] == {**clean.hall_models["hall1_x_l"],
                                            "a": pytest.approx(0.7, rel=1e-15)}
    assert clean.hall_models["hall1_x_l"]["a"] == 0.07  # the input's models are untouched
    for name in ROBOT.hall_names[1:]:
        assert bad.hall_models[name] == clean.hall_models[name]
    assert record == {"kind": "coeff", "column": "hall1_x_l", "from_s": None, "to_s": None,
                      "size": 10.0}
    # A sensor without a model gets the paper's, with its own side's sign.
    bare = inject_faults(inject_faults(clean, []), [])  # no change either way
    assert bare.hall_models == clean.hall_models and bare.extra_meta == clean.extra_meta
    np.testing.assert_array_equal(bare.hall_v, clean.hall_v)
    no_models = dataclasses.replace(clean, hall_models={})
    bad = inject_faults(no_models, [Fault.parse("coeff:hall1_x_r=2")])
    assert bad.hall_models == {"hall1_x_r": {"a": 0.14, "b": 2.87, "c": 2.22e5, "d": 8.43,
                                             "sign": -1, "unit": "deg"}}


def test_swap_exchanges_the_two_sides(clean):
    rows = _span(clean, 3, 5)
    bad, _ = _one(clean, "swap:hall2_y@3-5")
    _only_changed(clean, bad, ["hall2_y_l", "hall2_y_r"])
    left, right = _col(clean, "hall2_y_l"), _col(clean, "hall2_y_r")
    np.testing.assert_array_equal(_col(bad, "hall2_y_l"), np.where(rows, right, left))
    np.testing.assert_array_equal(_col(bad, "hall2_y_r"), np.where(rows, left, right))
    whole, record = _one(clean, "swap:hall1_x")
    np.testing.assert_array_equal(_col(whole, "hall1_x_l"), _col(clean, "hall1_x_r"))
    np.testing.assert_array_equal(_col(whole, "hall1_x_r"), _col(clean, "hall1_x_l"))
    assert (record["from_s"], record["to_s"]) == (0.0, float(clean.t[-1]))


def test_sign_negates_the_whole_session(clean):
    bad, record = _one(clean, "sign:gyro2_y")
    _only_changed(clean, bad, ["gyro2_y"])
    np.testing.assert_array_equal(_col(bad, "gyro2_y"), -_col(clean, "gyro2_y"))
    # A zero reading stays 0 (not -0, which a CSV would write as "-0").
    gyro = clean.gyro.copy()
    gyro[:50, ROBOT.gyro_names.index("gyro2_y")] = 0.0
    zeros = inject_faults(dataclasses.replace(clean, gyro=gyro), [Fault.parse("sign:gyro2_y")])
    assert (_col(zeros, "gyro2_y")[:50] == 0).all()
    assert not np.signbit(_col(zeros, "gyro2_y")[:50]).any()
    assert record == {"kind": "sign", "column": "gyro2_y", "from_s": None, "to_s": None,
                      "size": None}


def test_gap_removes_the_rows_and_keeps_the_truth(clean):
    rows = _span(clean, 3, 4)
    bad, record = _one(clean, "gap@3-4")
    assert bad.n_steps == clean.n_steps - rows.sum()
    np.testing.assert_array_equal(bad.t, clean.t[~rows])
    np.testing.assert_array_equal(bad.gyro, clean.gyro[~rows])
    np.testing.assert_array_equal(bad.hall_v, clean.hall_v[~rows])
    assert 1.0 < np.diff(bad.t).max() < 1.02  # the clock jumps over the gap
    np.testing.assert_array_equal(bad.mocap, clean.mocap)
    np.testing.assert_array_equal(bad.mocap_t, clean.mocap_t)
    assert record == {"kind": "gap", "column": None, "from_s": 3.0, "to_s": 4.0, "size": None}
    assert clean.n_steps == 1000


def test_faults_act_in_order_and_gaps_last(clean):
    faults = [Fault.parse(s) for s in ("noise:gyro1_x@2-6=0.5", "clip:gyro1_x@2-6=0.3",
                                       "gap@5-7", "dropout:hall1_x_l@6-8")]
    bad = inject_faults(clean, faults, seed=1)
    g = _col(bad, "gyro1_x")
    assert np.nanmax(np.abs(g[(bad.t >= 2) & (bad.t <= 6)])) == 0.3  # noise, then clipped
    assert not ((bad.t >= 5) & (bad.t <= 7)).any()
    assert np.isnan(_col(bad, "hall1_x_l")[(bad.t > 7) & (bad.t <= 8)]).all()
    assert [d["kind"] for d in bad.extra_meta["simulated_faults"]] == [
        "noise", "clip", "gap", "dropout"]
    # Adding a fault changes no other fault's draws (each has its own stream).
    alone = inject_faults(clean, faults[:1], seed=1)
    both = inject_faults(clean, [Fault.parse("flicker:hall1_x_l"), faults[0]], seed=1)
    np.testing.assert_array_equal(_col(both, "gyro1_x"), _col(alone, "gyro1_x"))


def test_the_record_round_trips_through_meta_json(clean, tmp_path):
    faults = [Fault.parse(s) for s in ("noise:hall2_y_r@1-2", "stuck:gyro3_x@4-5", "gap@6-7",
                                       "coeff:hall1_x_l=2", "swap:hall4_y")]
    bad = inject_faults(clean, faults, seed=4)
    write_session(bad, tmp_path / "s")
    meta = json.loads((tmp_path / "s" / "meta.json").read_text())
    assert meta["simulated_faults"] == bad.extra_meta["simulated_faults"]
    assert meta["hall_models"]["hall1_x_l"]["a"] == 0.14
    back = read_session(tmp_path / "s")
    assert back.extra_meta["simulated_faults"] == bad.extra_meta["simulated_faults"]
    assert back.extra_meta["simulation"] == clean.extra_meta["simulation"]
    assert back.n_steps == bad.n_steps
    # The resolved record makes the same faulty session again.
    again = inject_faults(clean, [Fault.from_json(d) for d in meta["simulated_faults"]],
                          seed=4)
    np.testing.assert_array_equal(again.hall_v, bad.hall_v)
    np.testing.assert_array_equal(again.gyro, bad.gyro)
    # A second injection appends to the record.
    more = inject_faults(back, [Fault.parse("sign:gyro1_x")])
    assert [d["kind"] for d in more.extra_meta["simulated_faults"]] == [
        "noise", "stuck", "gap", "coeff", "swap", "sign"]


def test_simulate_faults_keyword(clean):
    plain = simulate(ROBOT, "cyclic", seed=3, duration_s=10.0, drop_prob=0.02, faults=())
    np.testing.assert_array_equal(plain.gyro, clean.gyro)
    np.testing.assert_array_equal(plain.hall_v, clean.hall_v)
    assert set(plain.extra_meta) == {"simulation"}
    faults = [Fault.parse("noise:hall1_x_l@1-3"), Fault.parse("gap@4-5")]
    with_faults = simulate(ROBOT, "cyclic", seed=3, duration_s=10.0, drop_prob=0.02,
                           faults=faults)
    by_hand = inject_faults(clean, faults, seed=3)
    np.testing.assert_array_equal(with_faults.hall_v, by_hand.hall_v)
    np.testing.assert_array_equal(with_faults.t, by_hand.t)
    assert with_faults.extra_meta == by_hand.extra_meta


def test_device_seed_makes_trials_of_one_robot():
    def models(seed, device_seed=None):
        s = simulate(ROBOT, "cyclic", seed=seed, duration_s=2.0, device_seed=device_seed)
        return s.extra_meta["simulation"]["true_hall_models"], s.hall_v

    m1, v1 = models(1, device_seed=7)
    m2, v2 = models(2, device_seed=7)
    assert m1 == m2 and not np.array_equal(v1, v2)  # one robot, two trials
    assert models(1)[0] != models(2)[0]  # each seed its own robot by default
    assert models(1)[0] != m1 and models(7)[0] == m1


# ------------------------------------------------------------------------------- the command
def test_cli_writes_the_faults(tmp_path, capsys):
    out = tmp_path / "s"
    code = main(["simulate", str(out), "--seed", "3", "--duration", "10", "--drop-prob", "0.02",
                 "--fault", "disconnect:hall1_x_l@2-3", "--fault", "gap@5-6",
                 "--fault", "coeff:hall2_y_r=10"])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "faults: disconnect:hall1_x_l@2-3 gap@5-6 coeff:hall2_y_r=10" in err
    s = read_session(out)
    rows = (s.t >= 2) & (s.t <= 3)
    h = _col(s, "hall1_x_l")
    assert rows.sum() >= 99 and (h[rows & np.isfinite(h)] == 0.0).all()
    assert not ((s.t >= 5) & (s.t <= 6)).any() and 1.0 < np.diff(s.t).max() < 1.02
    assert s.hall_models["hall2_y_r"]["a"] == pytest.approx(0.7)
    assert [d["kind"] for d in s.extra_meta["simulated_faults"]] == ["disconnect", "gap",
                                                                     "coeff"]
    expected = simulate(ROBOT, "cyclic", seed=3, duration_s=10.0, drop_prob=0.02,
                        faults=[Fault.parse("disconnect:hall1_x_l@2-3"),
                                Fault.parse("gap@5-6"), Fault.parse("coeff:hall2_y_r=10")])
    np.testing.assert_allclose(s.hall_v, expected.hall_v, rtol=1e-8)
    np.testing.assert_array_equal(s.mocap_t, expected.mocap_t)


def test_cli_device_seed(tmp_path, capsys):
    def true_models(name, *extra):
        assert main(["simulate", str(tmp_path / name), "--duration", "2", "--quiet",
                     *extra]) == 0
        meta = json.loads((tmp_path / name / "meta.json").read_text())
        return meta["simulation"]["true_hall_models"], meta["simulation"]["device_seed"]

    a, da = true_models("a", "--seed", "1", "--device-seed", "9")
    b, db = true_models("b", "--seed", "2", "--device-seed", "9")
    c, dc = true_models("c", "--seed", "2")
    assert a == b and (da, db, dc) == (9, 9, 2)
    assert c != a


@pytest.mark.parametrize("spec, message", [
    ("nonsense:gyro1_x", "kckf simulate: error: fault 'nonsense:gyro1_x': unknown kind "
                         "'nonsense'; expected one of disconnect"),
    ("noise:gyro1_x@50-60", "kckf simulate: error: fault 'noise:gyro1_x@50-60': the span "
                            "50-60 s is outside the session (0-10 s)"),
    ("clip:hall1_x_l", "kckf simulate: error: fault 'clip:hall1_x_l': clip does not apply"),
])
def test_cli_bad_fault_is_one_line_and_exit_2(tmp_path, capsys, spec, message):
    out = tmp_path / "s"
    code = main(["simulate", str(out), "--duration", "10", "--fault", "gap@2-3",
                 "--fault", spec])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    lines = captured.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(message), captured.err
    assert not out.exists()  # nothing written
