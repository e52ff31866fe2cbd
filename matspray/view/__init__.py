"""`matspray view`: a browser viewer (viser) that shows a run's asset rendered by MatSpray's own renderer, the same
`relight.render_relit` that `relight` and `eval` use, and relights it live under any light.

One module per job: `scene` (what a run folder offers: variants, assets, photos, glb), `camera` (viser's camera <->
`Camera`), `lights` (the light choices, loading, rotation), `frames` (one picture per display mode, progressive sizes),
`photos` (the nearest training photo), `snapshot` (PNG into RUN/view/), `glb` (the exported mesh beside the Gaussians),
`gui` (the controls) and `server` (viser, one render thread per browser tab)."""
