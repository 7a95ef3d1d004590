"""service: the REST layer, storage and durable job queue around calib_core (calib_core never imports this)."""
