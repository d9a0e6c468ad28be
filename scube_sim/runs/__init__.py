"""The program's jobs, built from the layers below: scenario files (`scenario`: the schema and the
build of a run), `replay` (a scenario end to end into an output folder), the `make demo` job
(`demo`) and the four jobs of `scube-sim batch` (`batch_jobs`) on the task pool
(`scube_sim.parallel`)."""
