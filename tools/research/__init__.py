"""Studies and prototypes, measured and not part of the product (docs/history/)."""
