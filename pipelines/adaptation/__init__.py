"""`envisat adapt`: the detector taught a user's look from its own tracks (pseudo-labels, the look and range read off the silhouette edges)."""
