"""Benchmarks: jaxpose side by side with its peers (see DESIGN.md, "Benchmarks")."""
