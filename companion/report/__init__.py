"""Flight reports: a recorded flight read back (``flight_log``) and written as one HTML page (``html``)."""
