"""The frodo command line (launch, play, record, run, synth, eval, train, demo), launch file, parameters and Rerun viewer."""
