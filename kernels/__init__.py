"""Taichi kernels and the fields they work on. No YAML, no files, no PyBullet here."""
