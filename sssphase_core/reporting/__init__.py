"""Reports: the demo on the user's path (:mod:`.demo`), the HTML report (:mod:`.report`), figures
(:mod:`.figures`) and EXR export of sessions (:mod:`.export`)."""
