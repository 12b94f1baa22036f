"""The human-readable report: a list of blocks rendered as Markdown or as one HTML page."""

from __future__ import annotations

import html
import os
import re
from pathlib import Path
from typing import TYPE_CHECKING

import pandas as pd

from crs_study import __version__
from crs_study.analysis.sources import summarise_sources
from crs_study.paths import recorded_path

if TYPE_CHECKING:  # the report's own module imports this one
    from crs_study.analysis.report import Analysis

#: The methods' references, by what uses them; the report cites those of the methods that
#: ran (:func:`references`).
REFERENCES = {
    "wilson": "Wilson EB (1927) Probable inference, the law of succession, and statistical "
              "inference. JASA 22:209. Brown LD, Cai TT, DasGupta A (2001) Interval estimation "
              "for a binomial proportion. Statist Sci 16:101.",
    "lme4": "Bates D, Maechler M, Bolker B, Walker S (2015) Fitting linear mixed-effects "
            "models using lme4. J Stat Softw 67(1).",
    "random_structure": "Barr DJ, Levy R, Scheepers C, Tily HJ (2013) Random effects "
                        "structure for confirmatory hypothesis testing: keep it maximal. J Mem "
                        "Lang 68:255. Matuschek H, Kliegl R, Vasishth S, Baayen H, Bates D "
                        "(2017) Balancing Type I error and power in linear mixed models. J Mem "
                        "Lang 94:305.",
    "bootstrap": "Halekoh U, Hojsgaard S (2014) A Kenward-Roger approximation and parametric "
                 "bootstrap methods for tests in linear mixed models: the R package pbkrtest. "
                 "J Stat Softw 59(9). Besag J, Clifford P (1991) Sequential Monte Carlo "
                 "p-values. Biometrika 78:301.",
    "fisher": "Fisher RA (1922) On the interpretation of chi-square from contingency tables, "
              "and the calculation of P. J R Stat Soc 85:87.",
    "mcnemar": "Fagerland MW, Lydersen S, Laake P (2013) The McNemar test for binary "
               "matched-pairs data: mid-p and asymptotic are better than exact conditional. "
               "BMC Med Res Methodol 13:91.",
    "holm": "Holm S (1979) A simple sequentially rejective multiple test procedure. Scand J "
            "Stat 6:65.",
    "effect_sizes": "Lakens D (2013) Calculating and reporting effect sizes. Front Psychol "
                    "4:863. Kerby DS (2014) The simple difference formula. Compr Psychol 3:11.",
    "information": "Miller GA, Nicely PE (1955) An analysis of perceptual confusions among "
                   "some English consonants. JASA 27:338. Miller GA (1955) Note on the bias of "
                   "information estimates. Panzeri S, Treves A (1996) Analytical estimates of "
                   "limited sampling biases in different information measures. Network 7:87.",
    "speed_accuracy": "Woltz DJ, Was CA (2006) Availability of related long-term memory "
                      "during and after attention focus in working memory. Mem Cognit 34:668. "
                      "Liesefeld HR, Janczyk M (2019) Combining speed and accuracy to control "
                      "for speed-accuracy trade-offs(?). Behav Res Methods 51:40.",
    "psychometric": "Wichmann FA, Hill NJ (2001) The psychometric function I. Percept "
                    "Psychophys 63:1293.",
    "quest_plus": "Watson AB (2017) QUEST+: a general multidimensional Bayesian adaptive "
                  "psychometric method. J Vis 17(3):10.",
    "staircase": "Levitt H (1971) Transformed up-down methods in psychoacoustics. J Acoust "
                 "Soc Am 49:467.",
}


def references(analysis: Analysis) -> list[str]:
    """The references of the methods this analysis used, in :data:`REFERENCES` order."""
    comparisons = analysis.primary.comparisons
    used = {"wilson", "information"}
    if any(c.test == "glmm" for c in comparisons):
        used.add("lme4")
        if analysis.primary.fits is not None:
            used.add("random_structure")
    if any(c.p_method == "bootstrap" for c in comparisons):
        used.add("bootstrap")
    if any(c.test == "fisher" for c in comparisons):
        used.add("fisher")
    methods = " ".join(t.method.lower() for t in analysis.secondary.tests)
    if "mcnemar" in methods or analysis.secondary.per_symbol:
        used.add("mcnemar")
    if analysis.secondary.per_symbol and analysis.plan.secondary.correction == "holm":
        used.add("holm")
    if any(t.effect_size is not None for t in analysis.secondary.tests):
        used.add("effect_sizes")
    if not analysis.speed_accuracy.efficiency_summary.empty:
        used.add("speed_accuracy")
    thresholds = analysis.thresholds
    adaptive = thresholds is not None and not thresholds.skipped
    if analysis.psychometric.fits or adaptive:
        used.add("psychometric")
    if adaptive and thresholds.design is not None:
        used.add("quest_plus" if "quest" in thresholds.design.procedure else "staircase")
    return [text for key, text in REFERENCES.items() if key in used]


def _fmt(value) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        if value != value:
            return "n/a"
        if value != 0 and (abs(value) < 1e-3 or abs(value) >= 1e5):
            return f"{value:.3g}"
        return f"{value:.4g}"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    return str(value)


def _plan_text(analysis: Analysis) -> str:
    path = analysis.data.plan_path
    if path is None:
        return f"Plan `{analysis.plan.name}` (given in Python, not read from a file). "
    return f"Plan `{recorded_path(path)}` (sha256 {analysis.plan_sha256[:12]}...). "


def _table(frame: pd.DataFrame) -> list[list[str]]:
    return [[str(c) for c in frame.columns]] + [[_fmt(v) for v in row]
                                                for row in frame.astype(object).values.tolist()]


def build_blocks(analysis: Analysis, charts: list[Path],
                 out: Path) -> list[tuple[str, object]]:
    """The report as ``(kind, content)`` blocks: h1, h2, p, list, table, image, code; written
    from the analysis's result objects."""
    plan, data = analysis.plan, analysis.data
    warnings = analysis.warnings
    images = {p.stem: os.path.relpath(p, out) for p in charts}
    blocks: list[tuple[str, object]] = [("h1", f"Analysis: {plan.name}"),
                                        ("p", f"**{analysis.headline}**")]
    if analysis.plan_lock is not None:
        blocks.append(("p", analysis.plan_lock.sentence()))
    if warnings:
        blocks.append(("h2", f"Warnings ({len(warnings)})"))
        for group, raised in analysis.warning_groups().items():
            blocks += [("p", f"**{group.capitalize()}** ({len(raised)})"),
                       ("list", list(raised))]
    blocks += [("h2", "Data"), ("p", (
        f"{analysis.n_participants} participant(s), {len(data.sessions)} session(s); "
        f"{len(data.trials)} of {len(data.all_trials)} trials analysed. "
        + _plan_text(analysis) +
        f"Chance level {100 * analysis.accuracy.chance:.1f} %, alpha {plan.alpha:g}."))]
    blocks += [("p", "Sessions by who answered and on what device (kind: `simulated` when "
                     "the responder is a simulated participant or the device is `sim://`):"),
               ("table", _table(pd.DataFrame(summarise_sources(data.sources))))]
    blocks += [("p", note) for note in data.source_notes]
    exclusions = pd.DataFrame(data.exclusion_counts).T
    if not exclusions.empty:  # conditions in the plan's order, as in every other table
        order = [c for c in plan.conditions if c in exclusions.columns]
        exclusions = exclusions[order + [c for c in exclusions.columns if c not in order]]
        exclusions.index.name = "excluded because"
        blocks += [("p", "Exclusions declared in the plan (trials per condition):"),
                   ("table", _table(exclusions.reset_index()))]
    accuracy = analysis.accuracy
    blocks += [("h2", "Accuracy"),
               ("p", "Pooled trials: `ci_low`, `ci_high` are the Wilson interval of all the "
                     "condition's trials together (trial level; it ignores differences "
                     "between participants)."),
               ("table", _table(accuracy.by_condition)),
               ("p", "Between participants: the mean of the participants' accuracies with "
                     "the t interval across participants (the figures of the headline and "
                     "the chart: they account for differences between participants)."),
               ("table", _table(accuracy.between_participants))]
    if "accuracy" in images:
        blocks.append(("image", images["accuracy"]))
    blocks += _primary_model_blocks(analysis)
    primary = analysis.primary.to_frame()
    if not primary.empty:
        blocks.append(("table", _table(primary[["condition", "reference", "estimate", "ci95",
                                                "ci_method", "ci95_wald", "p_value",
                                                "p_wald", "p_lr"]])))
    for comparison in analysis.primary.comparisons:
        penalised = comparison.penalised
        if penalised:
            blocks.append(("p", (
                f"`{comparison.condition}` against `{comparison.reference}`: the "
                "maximum-likelihood odds ratio is infinite (separation), so the table gives "
                "its one-sided profile limit. Penalised fit, for orientation only "
                f"({penalised['note']}; prior: {penalised['prior']}): odds ratio "
                f"{_fmt(penalised['odds_ratio'])}, Wald interval "
                f"{_fmt(penalised['ci95_wald'])}, Wald p {_fmt(penalised['p_wald'])}.")))
    effects = (analysis.primary.model or {}).get("random_effects") or {}
    profiled = {name: e for name, e in effects.items() if e.get("sd_ci95") is not None}
    if profiled:
        blocks.append(("p", "Random intercepts (standard deviation on the logit scale, "
                            "profile-likelihood interval): " + "; ".join(
                                f"{name} {_fmt(e['sd'])} {_fmt(e['sd_ci95'])}"
                                for name, e in profiled.items()) + "."))
    if analysis.primary.fits is not None:
        blocks += [("p", "The model as lme4's `summary(glmer(...))` prints it:"),
                   ("code", analysis.primary.fits.full.summary())]
    if analysis.primary.omnibus:
        omnibus = analysis.primary.omnibus
        blocks.append(("p", f"Omnibus likelihood-ratio test of condition: chi2({omnibus['df']})"
                            f" = {omnibus['statistic']:.3f}, p = {_fmt(omnibus['p_value'])}."))
    secondary = analysis.secondary.to_frame()
    if not secondary.empty:
        blocks += [("h2", "Secondary tests"), ("table", _table(secondary[[
            "condition", "method", "estimate", "ci95", "p_value", "effect_size",
            "effect_size_name", "n"]]))]
    for condition, table in analysis.secondary.per_symbol.items():
        blocks += [("p", f"Per {table.columns[0]}, `{condition}` against "
                         f"`{analysis.reference}` "
                         f"(McNemar mid-p, {plan.secondary.correction} correction):"),
                   ("table", _table(table))]
    blocks.append(("h2", "Confusions and information transfer"))
    rows = pd.DataFrame([{k: v for k, v in r.to_dict().items()
                          if k in ("condition", "bits", "ci95", "bits_plugin", "stimulus_bits",
                                   "relative", "n_trials", "n_no_response")}
                         for r in analysis.confusions.values()])
    blocks.append(("table", _table(rows)))
    for stem, path in images.items():
        if stem.startswith("confusion_"):
            blocks.append(("image", path))
    speed = analysis.speed_accuracy
    blocks += [("h2", "Speed against accuracy"), ("table", _table(speed.rt_summary)),
               ("table", _table(speed.efficiency_summary))]
    for stem in ("speed_accuracy", "caf"):
        if stem in images:
            blocks.append(("image", images[stem]))
    psychometric = analysis.psychometric
    blocks.append(("h2", "Psychometric functions"))
    if psychometric.skipped:
        blocks.append(("p", psychometric.note))
    else:
        blocks.append(("table", _table(psychometric.to_frame()[[
            "condition", "function", "threshold", "threshold_ci95", "alpha", "beta", "lapse",
            "guess"]])))
        if "psychometric" in images:
            blocks.append(("image", images["psychometric"]))
    thresholds = analysis.thresholds
    if thresholds is not None and not thresholds.skipped:
        design = thresholds.design
        blocks.append(("h2", "Adaptive thresholds"))
        blocks.append(("p", f"{design.procedure} chose {design.level_column} ({design.scale} "
                            f"scale); each threshold is the level identified at "
                            f"{design.target_rate:.3g} correct: the procedure's own estimate "
                            "(QUEST+ posterior, or the mean of the staircase's last "
                            "reversals) and a psychometric fit over all the trials, with "
                            "95 % intervals."))
        blocks.append(("list", [c.sentence(design.level_column)
                                for c in thresholds.comparisons] or
                       ["no condition could be compared (fewer than 2 participants with "
                        "thresholds in both)"]))
        blocks.append(("table", _table(thresholds.to_frame()[[
            "participant_id", "condition", "n_trials", "reversals", "procedure_threshold",
            "procedure_ci_low", "procedure_ci_high", "fit_threshold", "fit_ci_low",
            "fit_ci_high"]])))
        for stem in ("tracks", "thresholds"):
            if stem in images:
                blocks.append(("image", images[stem]))
    blocks += [("h2", "Methods and references"), ("list", references(analysis)),
               ("p", f"crs-study {__version__}, generated {analysis.generated_at}.")]
    return blocks


def _primary_model_blocks(analysis: Analysis) -> list[tuple[str, object]]:
    """The primary test's heading: the model fitted, the one the plan asked for, and every
    step of the plan's rule that led from one to the other."""
    plan = analysis.plan
    adaptive = analysis.thresholds is not None and not analysis.thresholds.skipped
    title = "Accuracy model (secondary: the thresholds answer an adaptive study)" if \
        adaptive else "Primary test"
    model = (analysis.primary.model or {})
    structure = model.get("structure")
    fitted = model.get("random_formula", "none")
    out: list[tuple[str, object]] = [("h2", title), ("p", (
        f"Mixed-effects logistic regression `correct ~ condition + {fitted}` "
        f"({plan.primary.method}); odds ratio against `{analysis.reference}`, "
        "likelihood-ratio test of condition with the random part as fitted."))]
    if structure:
        rule = (f"reduce ({', then '.join(structure['reduction'])})"
                if structure["singular_fit"] == "reduce" else "keep the singular fit")
        out.append(("p", f"Random structure stated by the plan: `{structure['structure']}`, "
                         f"here `{structure['planned']}`; rule for a singular or failing fit: "
                         f"{rule}."))
        if structure["reduced"]:
            out.append(("list", [f"`{step['random']}`: {step['action']}"
                                 for step in structure["steps"] if step["action"]]
                        + [f"`{structure['fitted']}`: fitted and used"]))
    return out


def render_markdown(blocks: list[tuple[str, object]]) -> str:
    lines: list[str] = []
    for kind, content in blocks:
        if kind == "h1":
            lines += [f"# {content}", ""]
        elif kind == "h2":
            lines += [f"## {content}", ""]
        elif kind == "p":
            lines += [str(content), ""]
        elif kind == "list":
            lines += [f"- {item}" for item in content] + [""]
        elif kind == "table":
            header, *rows = content
            lines.append("| " + " | ".join(header) + " |")
            lines.append("|" + "---|" * len(header))
            lines += ["| " + " | ".join(row) + " |" for row in rows]
            lines.append("")
        elif kind == "image":
            lines += [f"![{Path(str(content)).stem}]({content})", ""]
        elif kind == "code":
            lines += ["```", str(content), "```", ""]
    return "\n".join(lines)


#: Columns of an HTML table beyond which it is split into parts (the first column repeated in
#: each), so that no table scrolls sideways on a page of :data:`PAGE_WIDTH`.
HTML_TABLE_COLUMNS = 8
PAGE_WIDTH = "60em"
_STYLE = (f"body{{font-family:sans-serif;max-width:{PAGE_WIDTH};margin:auto;padding:0 1em}}"
          "table{border-collapse:collapse;margin:0.5em 0}"
          "td,th{border:1px solid #ccc;padding:2px 6px;font-size:90%;overflow-wrap:break-word}"
          ".headline{font-size:115%;border-left:5px solid #4477aa;background:#eef3f9;"
          "padding:0.6em 0.9em}"
          "code{background:#f3f3f3;padding:0 2px}pre{overflow-x:auto;font-size:85%}"
          "img{max-width:100%}")


def inline_html(text: str) -> str:
    """Markdown's inline marks as HTML: `code` and **strong** (everything else escaped)."""
    out = []
    for k, part in enumerate(re.split(r"(`[^`]*`)", str(text))):
        if k % 2:
            out.append(f"<code>{html.escape(part[1:-1])}</code>")
        else:
            out.append(re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", html.escape(part)))
    return "".join(out)


def split_table(table: list[list[str]], width: int = HTML_TABLE_COLUMNS
                ) -> list[list[list[str]]]:
    """A table of more than ``width`` columns as parts of at most ``width``, each starting
    with the first (key) column."""
    header = table[0]
    if len(header) <= width:
        return [table]
    rest = list(range(1, len(header)))
    step = width - 1
    return [[[row[0], *(row[i] for i in rest[k:k + step])] for row in table]
            for k in range(0, len(rest), step)]


def render_html(blocks: list[tuple[str, object]]) -> str:
    """One HTML page: Markdown's inline marks rendered, the headline (the bold paragraph
    after the title) set apart, wide tables split (:func:`split_table`)."""
    body: list[str] = []
    for kind, content in blocks:
        if kind in ("h1", "h2"):
            body.append(f"<{kind}>{inline_html(content)}</{kind}>")
        elif kind == "p":
            text = str(content)
            if len(body) == 1 and text.startswith("**") and text.endswith("**"):
                body.append(f'<p class="headline"><strong>{inline_html(text[2:-2])}'
                            "</strong></p>")
            else:
                body.append(f"<p>{inline_html(text)}</p>")
        elif kind == "list":
            body.append("<ul>" + "".join(f"<li>{inline_html(i)}</li>" for i in content)
                        + "</ul>")
        elif kind == "table":
            for part in split_table(content):
                header, *rows = part
                body.append("<table><tr>" + "".join(f"<th>{html.escape(h)}</th>"
                                                    for h in header)
                            + "</tr>" + "".join("<tr>" + "".join(
                                f"<td>{html.escape(c)}</td>" for c in row) + "</tr>"
                                for row in rows) + "</table>")
        elif kind == "image":
            body.append(f'<p><img src="{html.escape(str(content))}" '
                        f'alt="{html.escape(Path(str(content)).stem)}"></p>')
        elif kind == "code":
            body.append(f"<pre>{html.escape(str(content))}</pre>")
    return (f"<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>crs-study report"
            f"</title><style>{_STYLE}</style></head><body>\n" + "\n".join(body)
            + "\n</body></html>\n")


def write_report(out: Path, analysis: Analysis, charts: list[Path]) -> Path:
    """Write ``report.md`` or ``report.html`` (the plan's ``report.format``)."""
    blocks = build_blocks(analysis, charts, out)
    if analysis.plan.report.format == "html":
        path = out / "report.html"
        path.write_text(render_html(blocks), encoding="utf-8")
    else:
        path = out / "report.md"
        path.write_text(render_markdown(blocks), encoding="utf-8")
    return path
