"""Device and model-backend plugins (import name ``sssphase_plugins``), loaded through pluggy."""
