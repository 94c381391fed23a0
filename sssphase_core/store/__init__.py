"""The session store: sessions on disk (:mod:`.session`, format in ``SESSION_FORMAT.md``), atomic
writes (:mod:`.files`) and image files in and out (:mod:`.imageio`, :mod:`.exr`)."""
