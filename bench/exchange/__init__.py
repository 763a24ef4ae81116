"""Forecasts made outside pcfbench's process (docs/bring-your-own-method.md).

    questions.py   which samples a cell asks for and what every answer must echo (``Questions``)
    queries.py     ``pcfbench queries``: the query file (compressed NumPy), written and read
    submission.py  a submission file (NumPy): opened, a sample's forecast read from it
    check.py       a submission (NumPy, or the AV2 challenge's JSON) checked whole against a cell
    method.py      the ``submission`` method: a checked file's forecasts, scored as any method's
    challenge.py   the Argoverse 2 4D occupancy challenge's JSON, both ways
    commands.py    ``pcfbench queries``, ``pcfbench score``, ``pcfbench challenge ...``
"""
