"""``kckf demo``: the main job on the shipped sample sessions.

For every data set under ``data/`` (``<dataset>/train<i>``, ``<dataset>/test<i>``): fit the
KCKF on the training sessions, evaluate every method of the paper's Table 1 and the fitted
KCKF on the held-out test sessions, filtered and smoothed (the offline output), and write
tables, JSON, fitted parameters and figures.

The fit learns the sensor effects that pay on every data set measured (``DEMO_LEARN``;
``training/effects.py``): where each step takes the gyros' rate (the paper's Euler rule makes
the angles lag half a step) and the gyros' scale factors.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterator

from .._fitting._fit import FitConfig, fit, fit_info
from .._models._params import save_params
from .._sessions._atomic import atomic_write
from .._sessions._session import read_session
from ._report import (
    PAPER_TABLE_METHODS,
    evaluate_sessions,
    format_table,
    markdown_table,
    session_name,
)

#: The sensor effects the demo's fit learns (``FitConfig.learn``; docs/fitting.md).
DEMO_LEARN = ("gyro_timing", "gyro_scale")


def demo_sets(root: str) -> dict[str, dict[str, list[str]]]:
    """``{dataset: {"train": [...], "test": [...]}}`` from ``data/<dataset>/<split><i>``."""
    sets = {}
    for ds in sorted(os.listdir(root)):
        d = os.path.join(root, ds)
        if not os.path.isdir(d):
            continue
        split = {"train": [], "test": []}
        for s in sorted(os.listdir(d)):
            for key in split:
                if s.startswith(key) and os.path.isfile(os.path.join(d, s, "meta.json")):
                    split[key].append(os.path.join(d, s))
        if split["test"]:
            sets[ds] = split
    return sets


def run_demo(root: str, out: str, steps: int, learning_rate: float,
             progress: Callable[[str, int, dict], None] | None = None) -> Iterator[str]:
    """Run the demo on the data sets under ``root``, writing into ``out``; yields each data
    set's table and summary as text (for people) as soon as it is done.

    ``progress(dataset, steps, record)`` is called after every fitting step."""
    from .plots import plot_session

    os.makedirs(out, exist_ok=True)
    report = {}
    md = ["# kckf demo", "",
          f"Fitted KCKF: {steps} Adam steps on the training sessions, learning "
          f"{', '.join(DEMO_LEARN)} too; smoothed: the fitted KCKF's RTS smoother; every "
          "column is scored on the held-out test sessions (RMSE, deg).", ""]
    sets = demo_sets(root)
    n_pad = max(len(split["train"]) for split in sets.values())
    methods = [*PAPER_TABLE_METHODS, "kckf_fit", "kckf_fit_smoothed"]
    for ds, split in sets.items():
        train = [read_session(p, require_mocap=True) for p in split["train"]]
        test = [read_session(p, require_mocap=True) for p in split["test"]]
        robot = test[0].robot
        config = FitConfig(steps=steps, learning_rate=learning_rate, learn=DEMO_LEARN)
        result = fit(train, (), config, pad_trials_to=n_pad,
                     callback=None if progress is None else
                     (lambda r, ds=ds: progress(ds, config.steps, r)))
        params_path = os.path.join(out, f"{ds}_params.json")
        save_params(result.params, params_path, fit_info(result, train, (), config))
        doc, angles = evaluate_sessions(test, PAPER_TABLE_METHODS)
        fitted, fitted_angles = evaluate_sessions(test, ["kckf"], result.params)
        smoothed, smoothed_angles = evaluate_sessions(test, ["kckf"], result.params,
                                                      smooth=True)
        doc["methods"]["kckf_fit"] = fitted["methods"]["kckf"]
        doc["methods"]["kckf_fit_smoothed"] = smoothed["methods"]["kckf"]
        doc.pop("_nis_rows", None)
        angles["kckf_fit"] = fitted_angles["kckf"]
        angles["kckf_fit_smoothed"] = smoothed_angles["kckf"]
        doc["fit"] = {"params": params_path, "train_sessions": split["train"],
                      "steps": result.steps_done, "seconds": round(result.seconds, 2),
                      "train_rmse_deg": result.best_loss_deg}
        report[ds] = doc
        paper, fit_mean, smooth_mean = (doc["methods"][m]["mean_rmse_deg"]
                                        for m in ("kckf", "kckf_fit", "kckf_fit_smoothed"))
        title = (f"{ds}: RMSE (deg) on {len(test)} test session(s), joints {robot.spec} "
                 f"(paper Table 1 layout; KCKF fit = fitted on {len(train)} training "
                 f"session(s), learning {', '.join(DEMO_LEARN)}; smoothed = its RTS smoother)")
        md += [f"## {ds}", "", markdown_table(doc["methods"], robot, methods), ""]
        for i, s in enumerate(test):
            name = session_name(s.path)
            plot_session(s, {m: angles[m][i] for m in methods}, os.path.join(out, "figures"),
                         name, gaps=doc["gaps"].get(s.path, []),
                         faults=doc["faults"].get(s.path, []),
                         title=f"{name}: held-out test session, every column of the table")
        yield (format_table(doc["methods"], robot, methods, title) + "\n"
               f"fitted KCKF mean RMSE {fit_mean:.3f} deg = {100 * fit_mean / paper:.0f} % of "
               f"the paper-default KCKF's {paper:.3f} deg, smoothed {smooth_mean:.3f} deg "
               f"(fit: {result.seconds:.1f} s)")
    with atomic_write(os.path.join(out, "results.json")) as f:
        json.dump(report, f, indent=2)
    with atomic_write(os.path.join(out, "table.md")) as f:
        f.write("\n".join(md))
