"""The library's workflows, which run the estimators on logs: calibration (:mod:`.calibration`), the
online calibrator and its checkpoints (:mod:`.online`), pose planning (:mod:`.planning`), a log's
diagnosis before any solver runs (:mod:`.diagnosis`) and a result's validation (:mod:`.validation`)."""
