"""Experiment campaigns on dask.distributed: campaign files, resumable Parquet results,
grouped statistics over seeds and derived studies (``rhonn-harness campaign``)."""
