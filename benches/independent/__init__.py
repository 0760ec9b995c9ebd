"""The independent generator of blind gap-diagnosis cases (benches/gap_independent.py is its command): ``mechanics``
(FEM and probe contact), ``imaging`` (texture and B-mode), ``cases`` (timeline, hidden kinds, recordings),
``scoring`` (verdicts and the benchmark summary)."""
