"""The app layer: the `envisat` verbs and every pipeline that combines stages (design.md, Layers)."""
