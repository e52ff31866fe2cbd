"""The HTML pages of `matspray eval` (RUN/report.html) in parts: the page around the sections with its image viewer
(`markup`), the answer-first summary (`summary`), the loss plot (`plot`), the glossary (`glossary`) and what keeps
the machine's paths off the page (`paths`). Plain HTML, CSS and a few lines of JavaScript: the page works from disk,
offline, copied or zipped with its `report/` folder."""
