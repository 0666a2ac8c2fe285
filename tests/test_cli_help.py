"""The ``kckf`` command's help and global options (issue 47): every value an option takes is
in its command's ``--help``, from the tuples the code checks against; ``--quiet`` and
``--debug`` before or after the verb; ``--quiet`` silences messages, never the result."""

from __future__ import annotations

import argparse
import json
import logging
import re

import pytest

from kckf_jax import cli
from kckf_jax._fitting._fit import LOSSES
from kckf_jax._models._classes import KALMAN_METHODS, METHODS
from kckf_jax._models._effects import EFFECTS as LEARNABLE
from kckf_jax._models._fault_policy import FAULT_POLICIES
from kckf_jax._models._params import ALL_LEAVES, HALL_NOISE_MODELS
from kckf_jax._readings._gaps import ON_GAP
from kckf_jax._sessions._sim_faults import FAULT_KINDS
from kckf_jax._sessions._simulate import EFFECTS as SIM_EFFECTS
from kckf_jax._sessions._simulate import KINDS, KINEMATICS
from kckf_jax.cli import main

#: Each option with a closed set of values and the tuple the code checks it against.
CODE_TUPLES = {"--learn": LEARNABLE, "--freeze": ALL_LEAVES, "--loss": LOSSES,
               "--noise": HALL_NOISE_MODELS, "--kind": KINDS, "--kinematics": KINEMATICS,
               "--effect": tuple(SIM_EFFECTS), "--fault": FAULT_KINDS,
               "--faults": FAULT_POLICIES, "--on-gap": ON_GAP, "--method": METHODS}
#: Where a command checks an option against another tuple than the rest.
CODE_TUPLES_OF = {("fit", "--method"): KALMAN_METHODS}


def _commands(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()):
    """``(verb path, parser)`` for the main parser and every (sub-)command's."""
    yield prefix, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _commands(sub, (*prefix, name))


def _closed_options(parser: argparse.ArgumentParser):
    """``(action, values)`` for every option of ``parser`` that takes a closed set: argparse's
    ``choices`` (a sub-command's names too) or the values the code checks (``accepted``)."""
    for action in parser._actions:
        values = getattr(action, "accepted", None) or action.choices
        if values:
            yield action, tuple(values)


def _flat(text: str) -> str:
    """Help text as one line: argparse wraps lines, at spaces and after hyphens."""
    return re.sub(r"(?<=\w-) (?=\w)", "", re.sub(r"\s+", " ", text))


def _names(value: str, text: str) -> bool:
    """``value`` appears in ``text`` as itself, not inside a longer name."""
    return re.search(rf"(?<![\w.]){re.escape(value)}(?!\w)", text) is not None


COMMANDS = list(_commands(cli.build_parser()))


@pytest.mark.parametrize("verb, parser", COMMANDS, ids=[" ".join(v) or "kckf" for v, _ in COMMANDS])
def test_every_accepted_value_is_in_the_help(verb, parser):
    text = _flat(parser.format_help())
    for action, values in _closed_options(parser):
        for value in values:
            assert _names(value, text), f"kckf {' '.join(verb)} --help lacks {value!r}"
            if action.option_strings:  # the option's own description names each value
                assert _names(value, _flat(action.help or "")), (
                    f"kckf {' '.join(verb)} {action.option_strings[-1]}: help lacks {value!r}")


def test_the_values_in_the_help_are_the_code_s_own():
    """Each closed option offers exactly the tuple the code checks it against, so the help
    cannot drift from the code (a new effect, method, loss or policy appears by itself)."""
    seen = set()
    for verb, parser in COMMANDS:
        for action, values in _closed_options(parser):
            for opt in set(action.option_strings) & set(CODE_TUPLES):
                want = CODE_TUPLES_OF.get((" ".join(verb), opt), CODE_TUPLES[opt])
                assert values == tuple(want), (verb, opt)
                seen.add(opt)
    assert seen == set(CODE_TUPLES)


def test_fit_help_names_every_learnable_effect(capsys):
    with pytest.raises(SystemExit):
        main(["fit", "--help"])
    text = _flat(capsys.readouterr().out)
    assert "gyro_timing" in text and all(_names(e, text) for e in LEARNABLE)


def test_top_level_help_documents_quiet_and_debug(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = _flat(capsys.readouterr().out)
    assert "--debug" in text and "--quiet" in text and "pyxdf" in text
    assert "before or after the verb" in text


@pytest.mark.parametrize("verb", [v for v, _ in COMMANDS if v and v != ("experiment",)],
                         ids=lambda v: " ".join(v))
def test_quiet_and_debug_before_or_after_the_verb(verb):
    parser = cli.build_parser()
    required = {("simulate",): ["S"], ("filter",): ["S", "-o", "x.csv"],
                ("evaluate",): ["S"], ("fit",): ["S", "-o", "p.json"],
                ("stream",): ["--source", "udp://127.0.0.1:1"], ("export",): ["-o", "x"],
                ("observability",): ["--joints", "x"]}.get(verb, [])
    plain = parser.parse_args([*verb, *required])
    assert plain.quiet is False and plain.debug is False
    for argv in (["--quiet", "--debug", *verb, *required], [*verb, *required, "--quiet", "--debug"],
                 ["--quiet", *verb, *required, "--debug"]):
        args = parser.parse_args(argv)
        assert args.quiet is True and args.debug is True, argv
    if len(verb) == 2:  # kckf experiment --quiet NAME
        args = parser.parse_args([verb[0], "--quiet", verb[1], "--debug"])
        assert args.quiet is True and args.debug is True


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("help") / "s1")
    assert main(["simulate", path, "--duration", "4", "--joints", "x,y", "--quiet"]) == 0
    return path


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_quiet_evaluate_before_or_after_the_verb_prints_the_table(session, tmp_path, capsys,
                                                                 monkeypatch):
    import kckf_jax.cli.plots

    for name in ("plot_session", "plot_diagnostics"):  # the figures are test_cli.py's
        monkeypatch.setattr(kckf_jax.cli.plots, name, lambda *a, **k: None)
    code, out, loud = _run(capsys, "evaluate", session, "--plot", str(tmp_path / "a"))
    assert code == 0 and out == "" and "KCKF" in loud and f"figures in {tmp_path / 'a'}" in loud
    code, out_before, before = _run(capsys, "--quiet", "evaluate", session,
                                    "--plot", str(tmp_path / "b"))
    assert code == 0
    code, out_after, after = _run(capsys, "evaluate", session, "--plot", str(tmp_path / "b"),
                                  "--quiet")
    assert code == 0
    assert out_before == out_after == "" and before == after
    # The table (the result) stays, the message about the figures goes.
    assert before == loud.replace(f"figures in {tmp_path / 'a'}\n", "")
    assert "KCKF" in before and "figures in" not in before


def test_quiet_evaluate_json(session, capsys):
    code, loud, _ = _run(capsys, "evaluate", session, "--json")
    assert code == 0
    code, out_before, err_before = _run(capsys, "--quiet", "evaluate", session, "--json")
    assert code == 0
    code, out_after, err_after = _run(capsys, "evaluate", session, "--json", "--quiet")
    assert code == 0
    assert out_before == out_after == loud and err_before == err_after == ""
    assert "kckf" in json.loads(out_before)["methods"]


def test_quiet_simulate_says_nothing(tmp_path, capsys):
    code, out, err = _run(capsys, "simulate", str(tmp_path / "s"), "--duration", "2",
                          "--joints", "x")
    assert code == 0 and out == "" and "wrote" in err
    code, out, err = _run(capsys, "--quiet", "simulate", str(tmp_path / "t"), "--duration", "2",
                          "--joints", "x")
    assert code == 0 and out == "" and err == ""


def test_quiet_stream_keeps_the_listening_line_and_the_packets(session, capsys):
    """The readiness line is the contract's (scripts wait for it): printed under --quiet too;
    the closing summary (a message) is not."""
    argv = ["stream", "--source", f"replay://{session}", "--max-packets", "20"]
    code, out, err = _run(capsys, *argv)
    assert code == 0 and "listening" in err and "kckf stream: packets 20" in err
    code, quiet_out, quiet_err = _run(capsys, "--quiet", *argv)
    assert code == 0 and quiet_out == out and len(out.splitlines()) == 20
    assert "listening" in quiet_err and "packets 20" not in quiet_err


@pytest.mark.parametrize("where", ["before", "after"])
def test_debug_turns_on_the_package_and_pyxdf_loggers(where, monkeypatch, capsys):
    seen = {}

    def probe(args):
        for name in ("kckf_jax", "pyxdf"):
            seen[name] = logging.getLogger(name).isEnabledFor(logging.DEBUG)
        logging.getLogger("kckf_jax.probe").debug("a debug line")
        return 0

    before = {n: logging.getLogger(n).isEnabledFor(logging.DEBUG) for n in ("kckf_jax", "pyxdf")}
    monkeypatch.setattr(cli, "cmd_observability", probe)
    argv = ["observability", "--joints", "x"]
    argv = ["--debug", *argv] if where == "before" else [*argv, "--debug"]
    code, out, err = _run(capsys, *argv)
    assert code == 0 and seen == {"kckf_jax": True, "pyxdf": True}
    assert "kckf_jax.probe: DEBUG: a debug line" in err
    # Afterwards (and without --debug) the loggers are as they were.
    code, out, err = _run(capsys, "observability", "--joints", "x")
    assert code == 0 and seen == before and "a debug line" not in err
