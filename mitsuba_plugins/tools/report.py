"""What :func:`mitsuba_plugins.tools.compare.compare` measured, written for people: the efficiency
table (text, Markdown, CSV, JSON), error-against-time curves of every metric and a
side-by-side image panel (PNG, matplotlib), the images themselves (EXR + PNG) and the
interactive page ``report.html`` (:mod:`mitsuba_plugins.tools.viewer`)."""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path

import numpy as np

from mitsuba_plugins import output
from mitsuba_plugins.tools import metrics, stats
from mitsuba_plugins.tools.compare import FLOOR_SHARE, Report

#: the files :func:`write_all` writes besides the images
TABLES = ("table.md", "table.csv", "results.json")
PLOTS = ("curves.png", "panel.png")
PAGE = "report.html"

COLUMNS = (  # header, Row attribute, format
    ("integrator", "integrator", "{}"),
    ("reference", "reference", "{}"),
    ("spp", "spp", "{}"),
    ("time [s]", "seconds", "{:.3f}"),
    ("rel. MSE", "rel_mse", "{:.3e}"),
    ("efficiency", "efficiency", "{:.4g}"),
    ("time / built-in", "time_ratio", "{:.3f}"),
    ("rel. MSE / built-in", "rel_mse_ratio", "{:.3f}"),
    ("eff. / built-in", "efficiency_ratio", "{:.3f}"),
    ("rel. MSE (top 0.1% out)", "rel_mse_trimmed", "{:.3e}"),
    ("MAPE", "mape", "{:.4f}"),
    ("SMAPE", "smape", "{:.4f}"),
    ("FLIP", "flip", "{:.4f}"),
    ("time to unit var. [s]", "ttuv", "{:.3e}"),
    ("NaN/Inf samples", "invalid", "{}"),
    ("ignores", "ignores", "{}"),
)


def _cell(value, fmt: str) -> str:
    if (isinstance(value, float) and math.isnan(value)) or value == "":
        return "-"
    return fmt.format(value)


def table(report: Report, markdown: bool = False) -> str:
    """The efficiency table, one row per integrator, aligned for a terminal or as Markdown."""
    head = [c[0] for c in COLUMNS]
    body = [[_cell(getattr(r, attr), fmt) for _, attr, fmt in COLUMNS] for r in report.rows]
    if markdown:
        line = lambda cells: "| " + " | ".join(cells) + " |"  # noqa: E731
        return "\n".join([line(head), "|" + "|".join("---" for _ in head) + "|"] + [line(b) for b in body])
    widths = [max(len(x) for x in col) for col in zip(head, *body)]
    line = lambda cells: "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"  # noqa: E731
    return "\n".join([line(head), "|" + "|".join("-" * (w + 2) for w in widths) + "|"] + [line(b) for b in body])


def legend(report: Report) -> str:
    """What the columns mean, and where a reference's own noise limits them."""
    how = (f"equal time: each integrator rendered passes of {report.spp_per_pass} spp until "
           f"{report.time_budget:g} s were spent" if report.mode == "equal-time" else
           f"equal spp: {report.rows[0].passes} passes of {report.spp_per_pass} spp each")
    floors = report.floors()
    lines = [f"{report.scene} ({how}; integrators take turns pass by pass, compilation excluded).",
             f"rel. MSE = mean((x - ref)^2 / (ref^2 + {stats.REL_MSE_EPS})) against the reference "
             "(high spp, independent seeds) minus the reference's own rel. MSE; "
             "efficiency = 1 / (rel. MSE x time); ratios are to the built-in row with the same "
             "reference. Beside it (not noise-corrected but the trimmed one): rel. MSE without "
             f"the {100 * metrics.TRIM_SHARE:g}% largest pixel errors, MAPE = mean |x - ref| / "
             f"(ref + {metrics.APE_EPS}), SMAPE = mean 2 |x - ref| / (|x| + |ref| + "
             f"{metrics.APE_EPS}), HDR-FLIP (flip-evaluator), time to unit variance = rel. MSE "
             "x time."]
    for name, ref in report.references.items():
        lines.append(f"reference {name}: {ref.spp} spp in {ref.passes} passes, own rel. MSE "
                     f"{floors[name]:.2e}")
    for r in report.rows:
        if r.ignores:
            lines.append(f"WARNING: {r.integrator} ignores the {r.ignores} of this scene: its "
                         f"error against {r.reference} counts the light it leaves out, and no "
                         "row is compared with it (ratios '-').")
    limited = [r.integrator for r in report.rows
               if floors[r.reference] > FLOOR_SHARE * r.rel_mse_measured]
    if limited:
        lines.append(f"WARNING: for {', '.join(limited)} the reference's own rel. MSE is over "
                     f"{100 * FLOOR_SHARE:.0f}% of the measured one; raise --ref-spp for a "
                     "reliable figure.")
    return "\n".join(lines)


def image_name(integrator_label: str) -> str:
    """File stem of an integrator's image (``path_rr:max_depth=5`` -> ``path_rr_max_depth-5``)."""
    return integrator_label.replace(":", "_").replace("=", "-").replace("/", "-")


def output_names(labels: list[str]) -> list[str]:
    """Every file name :func:`write_all` writes for integrators of these labels."""
    images = [image_name(name) + ext for name in labels for ext in (".exr", ".png")]
    return list(TABLES) + list(PLOTS) + [PAGE] + images


def write_tables(report: Report, out: Path) -> list[Path]:
    """``table.md``, ``table.csv`` and ``results.json`` (rows with their curves) in ``out``.
    Non-finite numbers are written as empty CSV cells and JSON ``null``."""
    md, csv_path, js = (out / name for name in TABLES)
    output.write_text(md, table(report, markdown=True) + "\n\n" + legend(report) + "\n")
    rows = [{k: v for k, v in r.to_dict().items() if not k.startswith("curve_")}
            for r in report.rows]
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    output.write_text(csv_path, text.getvalue())
    output.write_json(js, {**report.to_dict(), "null_means": output.JSON_NULL_MEANS}, indent=1)
    return [md, csv_path, js]


def write_images(report: Report, out: Path) -> list[Path]:
    """Each integrator's mean image as EXR and sRGB PNG."""
    paths = []
    for row in report.rows:
        exr = out / f"{image_name(row.integrator)}.exr"
        output.write_exr(exr, row.image)
        output.write_png(exr.with_suffix(".png"), row.image)
        paths.append(exr)
    return paths


def srgb(image: np.ndarray) -> np.ndarray:
    """Linear RGB (or gray) -> displayable sRGB in [0, 1] (clamped, no exposure change)."""
    x = np.clip(np.asarray(image, np.float64), 0.0, 1.0)
    x = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return x[..., 0] if x.ndim == 3 and x.shape[2] == 1 else x[..., :3]


def _pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _colors(report: Report) -> dict:
    plt = _pyplot()
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    return {r.integrator: cycle[i % len(cycle)] for i, r in enumerate(report.rows)}


def plot_curves(report: Report, path: Path, title: str | None = None) -> Path:
    """Every metric of the running estimate against seconds, log-log, one panel each (the
    first, relative MSE with the reference's noise subtracted, is the one efficiency is
    defined on); built-ins dashed, each reference's own rel. MSE dotted for scale."""
    plt = _pyplot()
    colors = _colors(report)
    fig, axes = plt.subplots(2, 3, figsize=(13.5, 7.6), dpi=100)
    axes = axes.ravel()
    for ax, name in zip(axes, metrics.NAMES):
        for r in report.rows:
            ax.loglog(r.curve_seconds, np.maximum(r.curve(name), 1e-12), "--" if r.builtin else "-",
                      marker=".", color=colors[r.integrator],
                      label=r.integrator + (" (built-in)" if r.builtin else ""))
        if name == "rel_mse":
            for ref_name, floor in report.floors().items():
                ax.axhline(floor, color="gray", linestyle=":", linewidth=1)
                ax.annotate(f"reference {ref_name}'s own", (ax.get_xlim()[0], floor), fontsize=7,
                            color="gray", va="bottom")
        ax.set_xlabel("render time [s] (compilation excluded)")
        ax.set_ylabel(metrics.TITLES[name])
        ax.grid(True, which="both", alpha=0.25)
    handles, names = axes[0].get_legend_handles_labels()
    axes[-1].axis("off")
    axes[-1].legend(handles, names, fontsize=9, loc="center")
    fig.suptitle(title or f"{Path(report.scene).stem}: error against time")
    fig.tight_layout()
    output.save_figure(fig, path)
    plt.close(fig)
    return path


def plot_panel(report: Report, path: Path, title: str | None = None) -> Path:
    """Top: each reference and each integrator's image (sRGB). Bottom: each reference's
    relative standard error and each integrator's relative squared error, one log scale."""
    plt = _pyplot()
    from matplotlib.colors import LogNorm
    refs = list(report.references.items())
    n = len(refs) + len(report.rows)
    fig, axes = plt.subplots(2, n, figsize=(2.3 * n + 0.8, 5.0), dpi=120, squeeze=False)
    maps = [metrics.reference_rel_var(ref) for _, ref in refs]
    maps += [metrics.pixel_rel_se(r.image, report.references[r.reference].mean) for r in report.rows]
    positive = np.concatenate([m[m > 0].ravel() for m in maps] + [np.array([1e-8])])
    norm = LogNorm(vmin=max(np.percentile(positive, 1), 1e-8), vmax=max(np.percentile(positive, 99.5), 1e-7))
    tops = [(f"reference\n{name} ({ref.spp} spp)", ref.mean) for name, ref in refs]
    tops += [(f"{r.integrator}\n{r.spp} spp, {r.seconds:.2f} s", r.image) for r in report.rows]
    bottoms = [f"ref. rel. variance\nmean {m.mean():.2e}" for m in maps[:len(refs)]]
    bottoms += [f"rel. squared error\nrel. MSE {r.rel_mse:.2e}" for r in report.rows]
    for k, ((text, image), err, below) in enumerate(zip(tops, maps, bottoms)):
        axes[0, k].imshow(srgb(image), cmap="gray" if image.shape[-1] == 1 else None,
                          vmin=0, vmax=1, interpolation="nearest")
        axes[0, k].set_title(text, fontsize=8)
        im = axes[1, k].imshow(np.maximum(err, norm.vmin), norm=norm, cmap="inferno",
                               interpolation="nearest")
        axes[1, k].set_title(below, fontsize=8)
        for ax in axes[:, k]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.colorbar(im, ax=axes[1, :].tolist(), fraction=0.02, pad=0.01)
    fig.suptitle(title or f"{Path(report.scene).stem} ({report.mode})", fontsize=10)
    output.save_figure(fig, path, bbox_inches="tight")
    plt.close(fig)
    return path


def write_all(report: Report, out: Path) -> dict:
    """Tables, images, ``curves.png``, ``panel.png`` and ``report.html`` in ``out``;
    returns their paths."""
    from mitsuba_plugins.tools import viewer
    names = output_names([r.integrator for r in report.rows])
    output.check_targets([out / name for name in names])
    check_not_foreign(out, names)
    with output.all_or_nothing():       # every file, or none
        written = {"tables": write_tables(report, out), "images": write_images(report, out),
                   "curves": plot_curves(report, out / PLOTS[0]),
                   "panel": plot_panel(report, out / PLOTS[1])}
        written["page"] = viewer.write_page(report, out / PAGE, COLUMNS, legend(report),
                                            curves=output.staged(written["curves"]))
    return written


def written_by_compare(folder: Path) -> bool:
    """Whether ``folder`` holds the ``results.json`` of an earlier ``compare``."""
    import json
    try:
        with open(Path(folder) / TABLES[2], encoding="utf-8") as f:
            return "rel_mse_definition" in json.load(f)
    except (OSError, ValueError, TypeError):
        return False


def check_not_foreign(folder, names) -> None:
    """Refuse an output folder that holds files of these ``names`` which ``compare`` did
    not write (a user's own ``table.md`` or ``panel.png`` was overwritten)."""
    folder = Path(folder)
    present = [n for n in names if (folder / n).exists()]
    if present and not written_by_compare(folder):
        raise output.OutputError(
            f"-o/--output '{folder}' holds {', '.join(present[:4])}"
            f"{' ...' if len(present) > 4 else ''} that compare did not write (no results.json "
            "of an earlier compare there); choose a new or empty folder")

