"""The answer of a power analysis: the curve, its Monte Carlo error, the one line, the chart.

Columns of :meth:`PowerResult.to_frame` (one row per point and comparison):

=================  =========================================================================
participants       N, participants per simulated study
repetitions        test trials per participant in each (condition, symbol, level) cell
comparison         the condition tested against ``reference``
studies            simulated studies at this point
significant        studies whose primary p (as ``analyze`` reports it) is below alpha
power              ``significant / studies``
ci_low, ci_high    Clopper-Pearson 95 % interval of the power (the Monte Carlo error)
separated          studies where the condition was at 0 % or 100 % (LR test at the supremum)
full_failed        studies whose full model could not be fitted (Fisher's exact test used)
reduced_failed     studies whose reduced model could not be fitted (the Wald p used)
untested           studies with no test of this comparison (its coefficient dropped)
unconverged        studies whose fit ``fit_glmm`` flagged as not converged (p still used)
failed             full_failed + reduced_failed + untested + unconverged
test               the p of the point: the LR statistic against chi2, or where the plan's
                   test is the parametric bootstrap, against the LR statistics of as many
                   null studies of the point (the generating model without the effect)
boundary           studies with a variance estimated at 0 (a singular fit: legitimate)
reduced_models     studies whose model the plan's rule reduced (a singular maximal fit)
reference_fits     studies fitted by ``fit_glmm`` itself rather than the batched fits
wrong_direction    significant studies whose estimate has the opposite sign of the model's
mean_log_odds      mean estimated log odds ratio over the studies that have one
=================  =========================================================================
"""

from __future__ import annotations

import json
import textwrap
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats

from crs_study import __version__
from crs_study._display import Display, Displayed
from crs_study._figure import new_axes
from crs_study._files import os_errors, write_atomically
from crs_study.power_analysis.design import PowerDesign, PowerError
from crs_study.power_analysis.model import GenerativeModel
from crs_study.power_analysis.study import (
    FISHER,
    NONE,
    SEPARATED,
    WALD,
    TaskResult,
    calibrated_pvalues,
    lr_statistic,
    recorded_parameters,
)


@dataclass(frozen=True)
class Answer:
    """Where the curve first reaches the target, for one comparison and repetition count.

    ``n`` the smallest N simulated with power >= target (None: not reached); ``low`` the
    smallest N whose interval reaches the target (the true crossing may be that early),
    ``high`` the smallest N whose whole interval is at or above it (None: beyond the curve).
    """

    comparison: str
    repetitions: int
    n: int | None
    low: int | None
    high: int | None
    first: int
    last: int
    power_at_last: float
    ci_at_last: tuple[float, float]

    def to_dict(self) -> dict:
        return {"comparison": self.comparison, "repetitions": self.repetitions, "n": self.n,
                "low": self.low, "high": self.high, "power_at_last": self.power_at_last,
                "ci_at_last": list(self.ci_at_last)}


@dataclass(frozen=True, repr=False)
class PowerResult(Displayed):
    """A power curve (see the module docstring for :meth:`to_frame`'s columns).

    ``raw`` keeps the per-study arrays (point x study [x comparison]): ``p_value``,
    ``kind``, ``log_odds``, ``theta`` (the full model's estimates: fixed effects, then
    SDs), ``converged``, ``boundary``, ``reference``; ``points`` the (participants,
    repetitions) of axis 0.
    """

    design: PowerDesign
    model: GenerativeModel
    points: tuple[tuple[int, int], ...]
    raw: dict = field(repr=False)
    seed: int = 0
    target: float = 0.8
    fidelity: str = "model"
    backend: str = "this process"
    seconds: float = 0.0
    cpu_seconds: float = 0.0
    notes: tuple[str, ...] = ()

    @property
    def n_studies(self) -> int:
        return int(self.raw["p_value"].shape[1])

    def pvalues(self) -> np.ndarray:
        """(point, study, comparison): the p ``analyze`` would report. Where the plan's test
        is the parametric bootstrap (``design.bootstrapped``), a study tested by its
        likelihood ratio gets the calibrated p of its statistic among the point's null
        studies (:func:`~crs_study.power_analysis.study.calibrated_pvalues`); otherwise the
        chi2 p (or the Wald, Fisher, supremum p its test gave)."""
        p = self.raw["p_value"].copy()
        null = self.raw.get("null_statistic")
        for i, (n, _) in enumerate(self.points):
            if null is None or not self.design.bootstrapped(n):
                continue
            for j in range(p.shape[2]):
                statistic = lr_statistic(self.raw, i, j)
                calibrated = calibrated_pvalues(statistic, null[i, :, j])
                p[i, :, j] = np.where(np.isfinite(statistic), calibrated, p[i, :, j])
        return p

    def significant(self) -> np.ndarray:
        """(point, study, comparison): the p ``analyze`` reports is below alpha."""
        p = self.pvalues()
        return np.isfinite(p) & (p < self.design.alpha)

    def to_frame(self) -> pd.DataFrame:
        sig = self.significant()
        kind = self.raw["kind"]
        log_odds = self.raw["log_odds"]
        converged = self.raw["converged"]
        direction = np.sign(self.model.base.mean(axis=(0, 1))[1:]
                            - self.model.base.mean(axis=(0, 1))[0])
        rows = []
        for i, (n, r) in enumerate(self.points):
            for j, comparison in enumerate(self.design.comparisons):
                k = int(sig[i, :, j].sum())
                S = sig.shape[1]
                ci = stats.binomtest(k, S).proportion_ci(0.95, method="exact")
                tested = kind[i, :, j] != NONE
                full_failed = int((kind[i, :, j] == FISHER).sum())
                reduced_failed = int((kind[i, :, j] == WALD).sum())
                untested = int((~tested).sum())
                unconverged = int((~converged[i] & tested & (kind[i, :, j] != FISHER)).sum())
                estimates = log_odds[i, :, j]
                wrong = sig[i, :, j] & (np.sign(estimates) == -direction[j]) & (direction[j] != 0)
                rows.append({
                    "participants": n, "repetitions": r, "comparison": comparison,
                    "reference": self.design.reference, "studies": S, "significant": k,
                    "power": k / S, "ci_low": float(ci.low), "ci_high": float(ci.high),
                    "separated": int((kind[i, :, j] == SEPARATED).sum()),
                    "full_failed": full_failed, "reduced_failed": reduced_failed,
                    "untested": untested, "unconverged": unconverged,
                    "failed": full_failed + reduced_failed + untested + unconverged,
                    "test": ("LR, bootstrap-calibrated (null studies of the point)"
                             if self.design.bootstrapped(n) else "LR, chi2"),
                    "boundary": int(self.raw["boundary"][i].sum()),
                    "reduced_models": int(self.raw["reduced"][i].sum()),
                    "reference_fits": int(self.raw["reference"][i].sum()),
                    "wrong_direction": int(wrong.sum()),
                    "mean_log_odds": float(np.nanmean(estimates)) if np.isfinite(
                        estimates).any() else float("nan")})
        return pd.DataFrame(rows)

    def answers(self) -> list[Answer]:
        """One :class:`Answer` per comparison and repetition count."""
        table = self.to_frame()
        out = []
        for (comparison, r), rows in table.groupby(["comparison", "repetitions"], sort=False):
            rows = rows.sort_values("participants")
            n = rows["participants"].to_numpy()
            last = rows.iloc[-1]
            out.append(Answer(comparison, int(r),
                              _first(n, rows["power"].to_numpy() >= self.target),
                              _first(n, rows["ci_high"].to_numpy() >= self.target),
                              _first(n, rows["ci_low"].to_numpy() >= self.target),
                              int(n[0]), int(n[-1]), float(last["power"]),
                              (float(last["ci_low"]), float(last["ci_high"]))))
        return out

    def _display(self) -> Display:
        participants = [n for n, _ in self.points]
        return Display(f"PowerResult of {self.design.protocol}", (
            ("answer", self.headline()),
            ("participants", f"{min(participants)} to {max(participants)}"),
            ("effect", self.effect_text()), ("alpha", f"{self.design.alpha:g}")),
            self.notes, ".to_frame(), .plot(), .save(folder)")

    def effect_text(self) -> str:
        """The effect the studies were drawn from, in words: each comparison's odds ratio
        for the typical participant (the exponent of the mean log-odds difference over
        symbols and levels), the typical participant's accuracy in each condition, and the
        ``--effect-scale`` applied (1: the effect as its source gives it)."""
        base = self.model.base
        accuracy = (1.0 / (1.0 + np.exp(-base))).mean(axis=(0, 1))
        parts = [f"odds ratio {c} / {self.design.reference} "
                 f"{np.exp(np.mean(base[..., k + 1] - base[..., 0])):.3g}"
                 for k, c in enumerate(self.design.comparisons)]
        typical = ", ".join(f"{c} {100 * a:.0f} %"
                            for c, a in zip(self.design.conditions, accuracy, strict=True))
        scale = self.model.details.get("effect_scale", 1.0)
        return f"{'; '.join(parts)} (typical participant: {typical}); --effect-scale {scale:g}"

    def headline(self) -> str:
        """One line per comparison and repetition count, e.g. ``80 % power at N = 12 (Monte
        Carlo 95 %: 8-12); 1000 studies per point; 0 fits failed``."""
        table = self.to_frame()
        failed, separated = int(table["failed"].sum()), int(table["separated"].sum())
        tail = f"{self.n_studies} studies per point; {failed} fit{'s' * (failed != 1)} failed"
        if separated:
            tail += f", {separated} separated (tested at the supremum, counted)"
        answers = self.answers()
        lines = []
        target = f"{100 * self.target:g} %"
        for a in answers:
            who = ""
            if len(self.design.comparisons) > 1:
                who += f"{a.comparison} vs {self.design.reference}: "
            if len({x.repetitions for x in answers}) > 1:
                who += f"{a.repetitions} repetitions: "
            if a.n is None:
                low, high = a.ci_at_last
                lines.append(f"{who}{target} power not reached by N = {a.last} (there "
                             f"{100 * a.power_at_last:.1f} %, Monte Carlo 95 %: "
                             f"{100 * low:.1f}-{100 * high:.1f} %); {tail}")
                continue
            span = _span(a)
            lines.append(f"{who}{target} power at N = {a.n} (Monte Carlo 95 %: {span}); "
                         f"{tail}")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        table = self.to_frame()

        return {
            "headline": self.headline(), "target": self.target, "alpha": self.design.alpha,
            "studies_per_point": self.n_studies, "seed": self.seed, "fidelity": self.fidelity,
            "design": self.design.to_dict(), "model": self.model.to_dict(self.design),
            "answers": [a.to_dict() for a in self.answers()],
            "points": json.loads(table.to_json(orient="records")),
            "recovery": self.recovery().to_dict(orient="records"),
            "backend": self.backend, "seconds": self.seconds, "cpu_seconds": self.cpu_seconds,
            "notes": list(self.notes),
            "software": {"name": "crs-study", "version": __version__}}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, allow_nan=False, default=_plain) + "\n"

    def save(self, directory: str | Path) -> tuple[Path, Path]:
        """Write ``power.json`` and the chart ``power.png`` into ``directory`` (made when
        missing), each replaced whole or not at all; returns their paths."""
        import io


        directory = Path(directory)
        text = self.to_json()
        buffer = io.BytesIO()
        self.plot().figure.savefig(buffer, format="png", dpi=120, metadata={"Software": None})
        with os_errors(PowerError, "write the power analysis", directory):
            directory.mkdir(parents=True, exist_ok=True)
            json_path, png_path = directory / "power.json", directory / "power.png"
            write_atomically(json_path, text)
            write_atomically(png_path, buffer.getvalue())
        return json_path, png_path

    def recovery(self) -> pd.DataFrame:
        """Per point and parameter: the mean estimate over the studies, its standard error
        and the number of studies with an estimate (``fit_glmm``'s ML estimates). The symbol
        intercept's SD is ``digit_sd`` for the digit set, ``symbol_sd`` for any other."""
        names = recorded_parameters(self.design)
        theta = self.raw["theta"]
        rows = []
        for i, (n, r) in enumerate(self.points):
            for k, name in enumerate(names):
                values = theta[i, :, k]
                values = values[np.isfinite(values)]
                rows.append({"participants": n, "repetitions": r, "parameter": name,
                             "studies": int(len(values)),
                             "mean": float(values.mean()) if len(values) else None,
                             "std_error": float(values.std(ddof=1) / np.sqrt(len(values)))
                             if len(values) > 1 else None})
        return pd.DataFrame(rows)

    def plot(self, ax=None):
        """Power against participants: a line per comparison and repetition count, the
        Monte Carlo 95 % band, the target line, and the share of failed or separated fits
        when there are any. Returns the Axes."""
        if ax is None:         # no pyplot state; shown in a notebook (crs_study._figure)
            ax = new_axes((7.0, 4.5))
        table = self.to_frame()
        groups = list(table.groupby(["comparison", "repetitions"], sort=False))
        for (comparison, r), rows in groups:
            rows = rows.sort_values("participants")
            label = []
            if len(self.design.comparisons) > 1:
                label.append(f"{comparison} vs {self.design.reference}")
            if len(groups) > 1 and len({g[0][1] for g in groups}) > 1:
                label.append(f"{r} repetitions")
            line, = ax.plot(rows["participants"], rows["power"], marker="o", markersize=3.5,
                            label=", ".join(label) or f"{comparison} vs {self.design.reference}")
            ax.fill_between(rows["participants"], rows["ci_low"], rows["ci_high"],
                            color=line.get_color(), alpha=0.2, linewidth=0)
            bad = rows["failed"] + rows["separated"]
            if bad.any():
                ax.plot(rows["participants"], bad / rows["studies"], linestyle=":",
                        color=line.get_color(),
                        label=f"share of failed or separated fits ({int(bad.sum())})")
        ax.axhline(self.target, color="0.3", linestyle="--", linewidth=1,
                   label=f"target {100 * self.target:g} %")
        for answer in self.answers():
            if answer.n is not None:
                ax.axvline(answer.n, color="0.3", linestyle=":", linewidth=1)
                ax.annotate(f"N = {answer.n}", (answer.n, self.target), xytext=(4, -14),
                            textcoords="offset points", fontsize=8, color="0.2")
        ax.set_ylim(-0.02, 1.02)
        ax.set_xlabel("participants (N)")
        ax.set_ylabel(f"power (p < {self.design.alpha:g})")
        source = {"observer": "simulated observer", "pilot": "pilot fit"}.get(
            self.model.source, self.model.source)
        ax.set_title("\n".join(textwrap.wrap(
            f"{self.design.protocol}: {self.n_studies} studies per point, effect from the "
            f"{source}: {self.effect_text()}", 80)) + "\nband: Monte Carlo 95 % interval",
            fontsize=8)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
        return ax


def _span(a: Answer) -> str:
    """The Monte Carlo range of N as words: ``8-12``, ``8``, ``4 or fewer``, ``36 to beyond
    40``."""
    low = f"{a.low} or fewer" if a.low == a.first else str(a.low)
    if a.high is None:
        return f"{low} to beyond {a.last}"
    if a.high == a.low:
        return low
    return f"{low} to {a.high}" if a.low == a.first else f"{a.low}-{a.high}"


def _first(n: np.ndarray, mask: np.ndarray) -> int | None:
    """The first ``n`` where ``mask`` holds (None: nowhere)."""
    return int(n[np.argmax(mask)]) if mask.any() else None


def merge(results: list[TaskResult]) -> dict[str, np.ndarray]:
    """The per-study arrays of the tasks, in study order (axis 1)."""
    ordered = sorted(results, key=lambda r: r.studies[0])
    keys = ("p_value", "kind", "log_odds", "theta", "converged", "boundary", "reduced",
            "reference", "loglike", "loglike_reduced", "null_statistic")
    return {k: np.concatenate([getattr(r, k) for r in ordered], axis=1) for k in keys
            if getattr(ordered[0], k) is not None}


def _plain(value):
    if isinstance(value, np.integer | np.floating | np.bool_):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
