// MathJax 3 for pymdownx.arithmatex (generic mode): typeset only what arithmatex marked, with
// the paper's equation numbers given by \tag{…} inside the display equations.
window.MathJax = {
  tex: {
    inlineMath: [["\\(", "\\)"]],
    displayMath: [["\\[", "\\]"]],
    processEscapes: true,
    processEnvironments: true,
    tags: "none"
  },
  options: {
    ignoreHtmlClass: ".*|",
    processHtmlClass: "arithmatex"
  }
};
