"""Markdown reports with PNG plots, from the evaluation summaries.

* ``zfusion eval ... --report DIR`` — :func:`write_eval_report` (:mod:`.eval_report`).
* ``python -m services.report NAME [--runs N] [--jobs J] [--out DIR]`` — the
  reproduction reports of ``docs/results/`` (``patent-3d``, ``patent-3d-60``,
  ``thesis-cep``, ``jammed-df-sweep``, ``air-picture``, ``df-multi``, ``df-moving``,
  ``patent-3d-maneuver``, or ``all``; ``docs/results/README.md`` says what each reproduces; :mod:`.cli`).

One module per concept: :mod:`.tables` (formatting, Markdown, writing a report and its
JSON), :mod:`.figures` (plots), :mod:`.eval_report`, and one per reproduction report
(:mod:`.patent`, :mod:`.thesis`, :mod:`.sweep`, :mod:`.many`, :mod:`.moving`, :mod:`.maneuver`), each
building its bundle of evaluation summaries and rendering it.

Every number in a report's tables is read from the JSON written next to it
(``NAME.json``: the command, the run count and every evaluation summary, each in the
``--json`` format of docs/design.md), and every summary comes from
:func:`services.evaluation.evaluate`, the code ``zfusion eval`` runs. Verdict sentences
are computed from the same numbers, so a regenerated report says what its data say.
"""

from .cli import DEFAULT_RUNS, RENDER, REPORT_NAMES, bundle_kind, main, make_report
from .eval_report import write_eval_report
from .maneuver import MANEUVER, build_maneuver, write_maneuver_report
from .many import MANY, build_many, many_verdicts, write_many_report
from .moving import build_moving, moving_rows, moving_verdicts, write_moving_report
from .patent import PATENT_TABLE, build_patent, patent_rows, write_patent_report
from .sweep import build_sweep, snr_db, sweep_variants, write_sweep_report
from .tables import dumps, fmt, inside_fraction, md_table
from .thesis import THESIS_CEP_M, build_thesis, thesis_methods, write_thesis_report

__all__ = [
    "DEFAULT_RUNS", "MANEUVER", "MANY", "PATENT_TABLE", "RENDER", "REPORT_NAMES", "THESIS_CEP_M", "build_maneuver", "build_many", "build_moving",
    "build_patent", "build_sweep", "build_thesis", "bundle_kind", "dumps", "fmt", "inside_fraction", "main",
    "make_report", "many_verdicts", "md_table", "moving_rows", "moving_verdicts", "patent_rows", "snr_db",
    "sweep_variants", "thesis_methods", "write_eval_report", "write_maneuver_report", "write_many_report", "write_moving_report",
    "write_patent_report", "write_sweep_report", "write_thesis_report",
]
