"""Learning: patch datasets from sessions (:mod:`.data`), PSP augmentations (:mod:`.augment`), the
SBH loss (:mod:`.losses`), encoder and decoder (:mod:`.models`), the training loops
(:mod:`.training`), model backends (:mod:`.backends`), kNN / footprint / image metrics
(:mod:`.evaluation`, :mod:`.metrics`, :mod:`.lpips`) and run logs (:mod:`.runlog`)."""
