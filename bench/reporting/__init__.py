"""Reports, regenerated from the store alone (docs/reports.md): reporting runs no method.

    report.py      collects the store's cells and writes every table and figure
    tables.py      leaderboards and per-step tables (Markdown, CSV, LaTeX); presets in tables.toml
    stats.py       intervals and paired comparisons (bootstrap over samples)
    figures.py     the figures (error by horizon, by range, the BEV gallery on request)
    htmlreport.py  the self-contained HTML page
    transfer.py    the zero-shot transfer table of trained methods
    labels.py      a cell's label in tables and figures
"""
