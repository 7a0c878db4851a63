"""What a model and a set of poses let one know, before or after a calibration: which parameters the
poses can see (:mod:`.identifiability`), the predicted closed-loop error (:mod:`.accuracy`), the
commands that compensate a calibrated model (:mod:`.compensation`) and the plausibility of a result
against its log (:mod:`.plausibility`)."""
