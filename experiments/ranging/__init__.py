"""The real-data protocol for 2-D ranging recordings (libRSF ``range2`` + odometry):
:mod:`.protocol` (folds, joint training of the sensor extras, selection on validation, test rows)
and :mod:`.report` (a folder end to end: ``results.csv`` per fold, figure, TensorBoard)."""
