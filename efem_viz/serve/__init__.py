"""What the two browser apps (viewer and annotator) share about serving: the access guard that opens every viser
server (`guard.start_server`: token, origin and host checks), the checks of every value a client sends
(`inputs`), how a server runs until it is stopped (`lifecycle`: its own SIGINT/SIGTERM handlers and the
serve-until-Ctrl+C wait), the camera (`camera`: the fitted view, *Reset view*, and the guard that brings back a
camera viser's W/A/S/D keys threw off the scene; fly-to), the pieces of an instance table (`table`: viser has no
table widget) and where outputs go by default (`outputs`: the user's data folder). Sits above the compute core and below
both apps, so neither app imports the other."""
