"""The paper's experiments (Ren et al. §4) on the simulated platform: Tables 4–6, Figs. 5–9.

Pure functions under a thin pipeline (:mod:`stewart_calib.pipelines.reproduce`)::

    reproduce(experiment, config, progress) -> Reproduction    # runs.py: nominal, ls frozen, online
    results_dict(reproduction, run_time_s) -> dict              # report.py: every number (results.json)
    tables_markdown(results) -> str                             # report.py: tables.md from results["tables"]
    write_recording(path, reproduction)                         # record.py: reproduce.rrd
    write_figures(directory, reproduction) -> [FigureFile]      # figures.py: Figs. 5–9 as PNG
    index_html(tables_md, figures, recording) -> str            # page.py: index.html, a tab per run

:mod:`.metrics` holds the measures: pose errors as the tracker sees them and as the simulator
knows them, one value per held pose.
"""

from .figures import write_figures
from .page import index_html
from .record import write_recording
from .report import results_dict, tables_markdown
from .runs import METHODS, MethodRun, Part, Reproduction, reproduce

__all__ = [
    "METHODS",
    "MethodRun",
    "Part",
    "Reproduction",
    "index_html",
    "reproduce",
    "results_dict",
    "tables_markdown",
    "write_figures",
    "write_recording",
]
