"""What measures the library (issue #34): `bench`, its benchmarks (ratios against baselines measured in the same
run); `evaluate`, accuracy and the closed loop on any pair with ground truth (`vergence accuracy`)."""
