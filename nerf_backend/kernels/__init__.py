"""Compiled CPU kernels (plain C, built on first use by ``build.py``)."""
