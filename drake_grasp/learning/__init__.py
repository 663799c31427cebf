"""Learning the distance CNN and GPD's classifier from simulated data: datasets
(`dataset`, `gpd_training`), the two CNN training loops (`training`, `dense_training` on `dense_labels`)
and what they share (`common`), ranking metrics (`cnn_metrics`), dataset pictures
(`datavis`).

Floor 9: imports `policies` and the floors below.
"""
