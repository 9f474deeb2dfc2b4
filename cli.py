#!/usr/bin/env python3
"""Run from a checkout: `python cli.py run scenes/zx120_excavation.yaml`. Same as the `opera-taichi` command."""
import sys

from opera_taichi.cli import main

if __name__ == "__main__":
    sys.exit(main())
