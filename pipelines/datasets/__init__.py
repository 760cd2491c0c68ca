"""`envisat dataset export`: a generated dataset in the formats the field trains on (layouts, the folder's README)."""
