"""Test beds shared by the tests, the demo and the benchmarks (no benchmark logic here)."""
