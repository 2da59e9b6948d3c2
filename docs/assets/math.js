// Typeset the site's math with the KaTeX shipped beside this file (no network). The Markdown
// pages hold it as pymdownx.arithmatex leaves it, \( \) and \[ \] in elements of class
// "arithmatex"; the notebooks' Markdown cells as their authors wrote it, $ $ and $$ $$.
document.addEventListener("DOMContentLoaded", function () {
  const inline = {left: "\\(", right: "\\)", display: false};
  const display = {left: "\\[", right: "\\]", display: true};
  const typeset = (selector, delimiters) => document.querySelectorAll(selector).forEach(
    (element) => renderMathInElement(element, {delimiters: delimiters, throwOnError: false}));
  typeset(".arithmatex", [display, inline]);
  typeset(".jp-RenderedMarkdown", [{left: "$$", right: "$$", display: true},
                                   {left: "$", right: "$", display: false}, display, inline]);
});
