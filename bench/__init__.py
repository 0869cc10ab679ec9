"""The benches: speed, memory, accuracy and reliability measurements of efem-viz, run from the checkout as modules,
``python -m bench.NAME [...]`` (e.g. ``python -m bench.real --preset real --seeds 0 1``).

`bench.common` is what they share: the CLIs' OpenMP wait policy (imported first, before torch), the record of the
machine a number was measured on (`machine`), and where results go (`result_path`, `write_result`):
``bench/results/<bench>/latest.json`` for a plain run (the run it replaces kept beside it, dated) and
``bench/results/<bench>/<bench>_<tag>.json`` for a named candidate or set. docs/BENCHMARKS.md says what each
number means, on which machine and beside what load it was measured.
"""
