"""Benchmarks: one script per question, run from the repository root as modules
(``python3 -m benchmarks.<name>``); ``benchmarks.harness`` is what they share.
docs/benchmarks.md lists the questions, the commands and the current answers."""
