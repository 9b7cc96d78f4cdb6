"""`soma view`: the twin in the browser (viser), fed by the in-process model, a live node or a resim bag."""
