"""What the two browser apps (viewer and annotator) share about serving: the access guard that opens every viser
server (`guard.start_server`: token, origin and host checks), the checks of every value a client sends
(`inputs`), and how a server runs until it is stopped (`lifecycle`: its own SIGINT/SIGTERM handlers and the
serve-until-Ctrl+C wait). Sits above the compute core and below both apps, so neither app imports the other."""
