"""The results store (README.md, "How data flows"): one folder per cell, written atomically, so an
interrupted run resumes without losing or duplicating rows.

    cells.py    cell identity (cell.json), per-sweep Parquet rows, atomic writes
    ranges.py   error-by-range bins stored beside the rows at run time (what the range figure reads)
"""
