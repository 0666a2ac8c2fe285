"""XDF recordings as real lab files leave them: cut short by a recorder that crashed, with an
empty motion-capture stream, damaged in the middle; and pyxdf's own log kept off stderr.

Every file is written here by the tests' own writer (``xdf_writer``) and cut or damaged here."""

from __future__ import annotations

import logging
import os
import shutil
import warnings

import numpy as np
import pytest
from helpers import error_of
from test_containers import T0, mocap_stream, sensor_stream, small_session, xdf_folder
from xdf_writer import chunk, write_xdf

from kckf_jax import SessionError, read_session
from kckf_jax._sessions._session import SessionWarning
from kckf_jax.cli import main

CHUNK = 40  # sensor samples per Samples chunk


def recording(folder, *, offsets_with_samples: bool, n: int = 250):
    """A session of ``n`` sensor rows as ``recording.xdf`` (sensors and mocap on two clocks,
    each with clock offsets), the reference session and the file's chunks."""
    s = small_session(n=n)
    clocks = dict(clock_offsets=[(T0 + k, 0.0) for k in range(6)])
    streams = [sensor_stream(s, chunk=CHUNK, **clocks), mocap_stream(s, chunk=CHUNK)]
    streams[1].clock_offsets = [(w, v) for w, v in streams[1].clock_offsets] * 2
    folder = xdf_folder(folder, s, streams)
    layout = write_xdf(os.path.join(folder, "recording.xdf"), streams,
                       offsets_with_samples=offsets_with_samples)
    return folder, read_session(folder), layout


def cut_copy(folder, at: int, dest) -> str:
    """``folder`` copied to ``dest`` with its ``recording.xdf`` cut to its first ``at`` bytes."""
    shutil.copytree(folder, dest)
    path = os.path.join(dest, "recording.xdf")
    with open(path, "rb") as f:
        head = f.read(at)
    with open(path, "wb") as f:
        f.write(head)
    return str(dest)


def read_noting(folder, **kwargs):
    """``(session, warnings' texts)``, or ``(None, [error])`` for a refusal."""
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        try:
            s = read_session(folder, **kwargs)
        except SessionError as e:
            return None, [str(e)]
    assert all(w.category is SessionWarning for w in got), [str(w.message) for w in got]
    return s, [str(w.message) for w in got]


# ---------------------------------------------------------------------- a file cut short


@pytest.mark.parametrize("offsets_with_samples",
                         [False, pytest.param(True, marks=pytest.mark.long)])
def test_every_cut_is_read_in_part_with_one_line_or_refused_when_nothing_remains(
        tmp_path, offsets_with_samples):
    """Cut anywhere (in a chunk's length, a header, a Samples chunk, a ClockOffset chunk, a
    footer, between chunks): the whole Samples chunks before the cut are read, exactly those,
    and one line says where the file stops and what was kept; refused only where no sensor
    sample remains. The mocap is used where both streams have clock offsets before the cut
    (LabRecorder writes them as it records: ``offsets_with_samples``), and said not to be
    where they do not (its stamps would be on another clock)."""
    folder, ref, layout = recording(tmp_path / "full", offsets_with_samples=offsets_with_samples)
    size = layout[-1][1]
    assert read_noting(folder)[1] == []  # the whole file: not a word
    places = {start + d for start, _, _, _ in layout for d in (0, 2, 7)}  # 2: in its length
    places |= set(range(5, size, size // 29))
    first_samples = next(end for _, end, tag, sid in layout if tag == 3 and sid == 1)
    outcomes = set()
    for at in sorted(p for p in places if 4 <= p < size):
        whole = [(tag, sid) for _, end, tag, sid in layout if end <= at]
        s, said = read_noting(cut_copy(folder, at, tmp_path / f"cut{at}"))
        rec = f"{tmp_path}/cut{at}/recording.xdf"
        assert len(said) == 1 and "\n" not in said[0], (at, said)
        if at < first_samples:  # no sensor sample before the cut
            assert s is None and said[0].startswith((f"{rec}: cut short at byte {at:,} (inside ",
                                                     f"{rec}: ends at byte {at:,} with")), said
            assert "nothing usable remains" in said[0], said
            outcomes.add("refused")
            continue
        assert s is not None, (at, said)
        n = min(CHUNK * whole.count((3, 1)), ref.n_steps)
        assert said[0].startswith((f"{rec}: cut short at byte {at:,} (inside ", f"{rec}: ends "
                                   f"at byte {at:,} without the footer of stream")), said
        assert f"sensors stream 'exoshell': {n:,} samples, t 0 to {ref.t[n - 1]:.3f} s" in said[0]
        np.testing.assert_allclose(s.t, ref.t[:n], rtol=0, atol=1e-9)
        np.testing.assert_array_equal(s.hall_v, ref.hall_v[:n])
        np.testing.assert_array_equal(s.gyro, ref.gyro[:n])
        synced = (4, 1) in whole and (4, 2) in whole
        m = min(CHUNK * whole.count((3, 2)), len(ref.mocap_t))
        if synced and m:
            assert f"motion-capture stream 'vicon': {m:,} samples to t " in said[0], said
            np.testing.assert_allclose(s.mocap_t, ref.mocap_t[:m], rtol=0, atol=1e-9)
            np.testing.assert_allclose(s.mocap, ref.mocap[:m], rtol=1e-12, atol=1e-15)
            outcomes.add("mocap kept")
        else:
            assert s.mocap is None
            assert ("motion-capture stream 'vicon' not used" in said[0]
                    or "motion-capture stream 'vicon': no samples (not used)" in said[0]), said
            outcomes.add("mocap not used")
    assert outcomes == {"refused", "mocap kept", "mocap not used"}


def test_the_line_for_a_cut_samples_chunk(tmp_path):
    """The whole message for the commonest cut (inside a Samples chunk, the recorder's clock
    offsets written as it recorded)."""
    folder, ref, layout = recording(tmp_path / "full", offsets_with_samples=True)
    start, end, tag, sid = [c for c in layout if c[2] == 3 and c[3] == 1][4]
    at = (start + end) // 2
    s, said = read_noting(cut_copy(folder, at, tmp_path / "cut"))
    rec = f"{tmp_path}/cut/recording.xdf"
    m = CHUNK * sum(1 for _, e, tag, sid in layout if e <= start and (tag, sid) == (3, 2))
    assert said == [
        f"{rec}: cut short at byte {at:,} (inside a Samples chunk of stream 'exoshell'; the whole "
        f"chunks end at byte {start:,}): a recording that was not closed (a recorder that "
        f"crashed?); read the whole chunks: sensors stream 'exoshell': 160 samples, t 0 to "
        f"{ref.t[159]:.3f} s; motion-capture stream 'vicon': {m} samples to t "
        f"{ref.mocap_t[m - 1]:.3f} s"]
    assert s.n_steps == 160 and s.has_truth
    assert error_of(cut_copy(folder, 30, tmp_path / "head")) == (
        f"{tmp_path}/head/recording.xdf: cut short at byte 30 (inside the file header; the "
        "whole chunks end at byte 4), before the sensors' stream and its samples: nothing "
        "usable remains (the whole chunks hold the streams: none)")


def test_a_cut_file_needed_for_its_mocap_is_refused_naming_the_cut(tmp_path):
    folder, _, layout = recording(tmp_path / "full", offsets_with_samples=False)
    at = next(start for start, _, tag, _ in layout if tag == 4)  # before every clock offset
    cut = cut_copy(folder, at, tmp_path / "cut")
    assert error_of(cut, require_mocap=True) == (
        f"{cut}/recording.xdf, stream 'vicon': not on the sensors' clock (the file ends at byte "
        f"{at:,}, before the clock offsets: streams 'exoshell' and 'vicon' have none); motion "
        "capture is needed to evaluate or to fit on the RMSE (kckf fit --loss nll fits on the "
        "Hall readings alone)")


def test_damage_in_the_middle_is_said_in_one_line(tmp_path):
    """Bytes no writer writes between two chunks, then a Boundary chunk (LabRecorder writes
    one every few seconds): pyxdf scans forward to it and reads on; the damage is said (not
    left in pyxdf's log), and nothing is lost here."""
    folder, ref, layout = recording(tmp_path / "full", offsets_with_samples=True)
    path = os.path.join(folder, "recording.xdf")
    with open(path, "rb") as f:
        raw = f.read()
    at = [c for c in layout if c[2] == 3][3][1]
    boundary = chunk(5, bytes.fromhex("43A546DCCBF5410FB30ED5467383CBE4"))
    with open(path, "wb") as f:
        f.write(raw[:at] + b"\x07\x07\x07" + boundary + raw[at:])
    s, said = read_noting(folder)
    assert said == [f"{path}: damaged: pyxdf skipped over what it could not read (Error reading "
                    "chunk length); the samples in those parts are lost"]
    np.testing.assert_array_equal(s.hall_v, ref.hall_v)


# ---------------------------------------------------------------------- empty mocap stream


def empty_mocap_folder(folder):
    s = small_session(n=300)
    empty = mocap_stream(s, stamps=np.zeros(0), values=np.zeros((0, s.robot.n_angles)))
    return xdf_folder(folder, s, [sensor_stream(s), empty]), s


def test_an_empty_mocap_stream_is_no_mocap(tmp_path):
    folder, ref = empty_mocap_folder(tmp_path / "s")
    s, said = read_noting(folder)
    assert said == [f"{folder}/recording.xdf, stream 'vicon': no samples: the motion-capture "
                    "stream is empty, so it gives no motion capture"]
    assert s.mocap is None and not s.has_truth
    np.testing.assert_array_equal(s.hall_v, ref.hall_v)
    assert error_of(folder, require_mocap=True) == (
        f"{folder}/recording.xdf, stream 'vicon': no samples; motion capture is needed to "
        "evaluate or to fit on the RMSE (kckf fit --loss nll fits on the Hall readings alone)")


@pytest.mark.filterwarnings("default::kckf_jax._sessions._session.SessionWarning")
def test_filter_runs_and_evaluate_refuses_on_an_empty_mocap_stream(tmp_path, capsys):
    folder, ref = empty_mocap_folder(tmp_path / "s")
    out = tmp_path / "est.csv"
    assert main(["filter", folder, "-o", str(out), "--quiet"]) == 0
    err = capsys.readouterr().err
    line = (f"kckf filter: warning: {folder}/recording.xdf, stream 'vicon': no "
            "samples: the motion-capture stream is empty, so it gives no motion capture")
    assert err.splitlines().count(line) == 1, err
    assert "pyxdf" not in err
    assert len(out.read_text().splitlines()) == ref.n_steps + 1
    assert main(["evaluate", folder, "--json"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err == (
        f"kckf evaluate: error: {folder}/recording.xdf, stream 'vicon': no samples; motion "
        "capture is needed to evaluate or to fit on the RMSE (kckf fit --loss nll fits on the "
        "Hall readings alone)\n")


# ---------------------------------------------------------------------- pyxdf's log


def no_clock_offsets_folder(folder) -> str:
    """A recording whose streams (on one clock) have no clock offsets: pyxdf logs a warning
    per stream."""
    s = small_session()
    return xdf_folder(folder, s, [sensor_stream(s, clock_offsets=()),
                                  mocap_stream(s, clock_offsets=(), stamps=s.mocap_t + T0)])


def test_pyxdf_logs_nothing_while_kckf_reads(tmp_path, caplog, capfd):
    import pyxdf

    folder = no_clock_offsets_folder(tmp_path / "s")
    path = os.path.join(folder, "recording.xdf")
    with caplog.at_level(logging.WARNING):
        pyxdf.load_xdf(path, synchronize_clocks=True, dejitter_timestamps=False)
    assert any(r.name.startswith("pyxdf") for r in caplog.records)  # it does log, alone
    caplog.clear()
    capfd.readouterr()
    logger = logging.getLogger("pyxdf")
    before = (logger.level, logger.propagate, list(logger.handlers))
    with caplog.at_level(logging.WARNING):  # where pyxdf's warnings went to stderr
        read_session(folder)  # no warning either (none is an error in this test run)
    assert [r for r in caplog.records if r.name.startswith("pyxdf")] == []
    assert capfd.readouterr() == ("", "")
    assert (logger.level, logger.propagate, list(logger.handlers)) == before  # restored


def test_pyxdf_logs_as_it_does_under_kckf_debug(tmp_path, caplog):
    """``kckf --debug`` sets the kckf_jax and pyxdf loggers to DEBUG: pyxdf's records then go
    out as pyxdf sends them."""
    folder = no_clock_offsets_folder(tmp_path / "s")
    caplog.set_level(logging.DEBUG, logger="kckf_jax")
    caplog.set_level(logging.DEBUG, logger="pyxdf")
    read_session(folder)
    texts = [r.getMessage() for r in caplog.records if r.name.startswith("pyxdf")]
    assert any("Segments and clock-segments differ" in t for t in texts), texts
    assert any("Importing XDF file" in t for t in texts), texts  # its INFO too
