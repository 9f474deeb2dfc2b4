"""Physics validation: analytic references (references.py), the validation cases run as ordinary scenes
(cases.py) and the report docs/validation.md with its plots (report.py)."""
