"""What the two browser apps (viewer and annotator) share about serving: the access guard that opens every viser
server (`guard.start_server`: token, origin and host checks) and the checks of every value a client sends
(`inputs`). Sits above the compute core and below both apps, so neither app imports the other."""
