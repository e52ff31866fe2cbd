"""`matspray export --web DIR`: a static page that relights the asset in the browser.

`detail` chooses the Gaussians the page draws, `pack` quantises them and the lights into the page's data scripts,
`page` writes the folder: index.html, the page's script (`src/*.js`, bundled with three.js from npm by `make setup`
into `dist/`) and the data. The page renders as `matspray relight` does (G-buffer, then split-sum shading;
`src/shaders.js`) and prefilters its light itself (`src/prefilter.js`), so that a dropped .hdr / .exr relights the
asset too."""

# dB: the page's frames against the whole asset's when it leaves out the Gaussians that add least (`detail`;
# measured in docs/dev/web.md)
DEFAULT_WEB_PSNR = 35.0
