"""Benchmarks behind `drsplat bench ...`. Each module defines `add_bench(subparsers)`."""
