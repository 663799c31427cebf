"""Learning the distance CNN and GPD's classifier from simulated data: the training set
(`dataset`: settings, seeds, one scene; `dataset_generate`: shards over workers;
`dataset_shards`: the format on disk and its reader; `folder_lock`: one run per folder),
GPD's training set (`gpd_training`), the two CNN training loops (`training`,
`dense_training` on `dense_labels` with `dense_rank`) and what they share (`common`),
ranking metrics (`cnn_metrics`), dataset pictures (`datavis`).

Floor 9: imports `policies` and the floors below.
"""
