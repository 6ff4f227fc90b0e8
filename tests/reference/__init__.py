"""Reference implementations kept only as test oracles (and as the benchmarks' "previous" baselines): the library
has one implementation of each algorithm, these are the older or plainer versions its results are compared with."""
