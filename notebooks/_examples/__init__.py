"""Importable example scripts behind the notebooks (smoke-tested at tiny sizes)."""
