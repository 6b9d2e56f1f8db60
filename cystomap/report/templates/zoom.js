document.addEventListener("click", function (e) {
  var open = document.querySelector(".zoom");
  if (open) { open.remove(); return; }
  if (e.target.tagName === "IMG" && e.target.closest("figure")) {
    var box = document.createElement("div"), img = document.createElement("img");
    box.className = "zoom"; img.src = e.target.src; img.alt = e.target.alt;
    box.appendChild(img); document.body.appendChild(box);
  }
});
