"""`envisat adapt`: the detector taught a user's frames from its own tracks (pseudo-labels, the camera response and range read off the silhouette edges)."""
