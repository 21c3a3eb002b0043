"""Learning and judging a dynamics model: the trainer (:mod:`~pets.learning.trainer`, its compiled step
:mod:`~pets.learning.compiled`), offline training on a data set (:mod:`~pets.learning.offline`) and the
long-horizon prediction error (:mod:`~pets.learning.evaluation`)."""
