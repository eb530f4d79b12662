"""Benchmarks: each module measures one thing and writes JSON results (and figures)."""
