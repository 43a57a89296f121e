"""Support for testing StreamSTGS and what is built on it, shipped with the library as `numpy.testing` is: imported by
the test suite and the benchmarks, never by the library itself. Needs the `test` extra (Hypothesis)."""
