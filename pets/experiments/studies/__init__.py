"""The studies of the comparison command, one module each: what a run records and the statistics over seeds."""
