"""Accuracy studies: terrain scans and joint logs compared with a run (`compare`), parameter sweeps (`study`) and
soil calibration (`calibrate`) on a Dask cluster.

scan.py       read scans (LAS/LAZ, PLY, XYZ/CSV, GeoTIFF, NPZ), grid them, place them in the machine frame
compare.py    terrain and joint metrics of a run against a scan, a log or another run; comparison.json
figures.py    the comparison's and the study's PNGs
study.py      STUDY.yaml, sampling, running the points on Dask, the table
calibrate.py  Optuna over the same points, a soil preset file out
"""
