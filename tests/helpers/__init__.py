"""Test helpers importable in worker processes (pytest puts tests/ on sys.path; children inherit it)."""
