"""Reading a field (exposures, weights, catalogues and its YAML config), cutting postage stamps and writing the shear catalogue."""
