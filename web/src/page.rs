//! The few page elements the viewer writes to (ids fixed by the page the server serves).

use wasm_bindgen::JsCast;
use web_sys::{Document, HtmlElement};

pub fn document() -> Option<Document> {
    web_sys::window()?.document()
}

fn element(id: &str) -> Option<HtmlElement> {
    document()?.get_element_by_id(id)?.dyn_into().ok()
}

/// Sets the text of element `id`, when the page has it.
pub fn set_text(id: &str, text: &str) {
    if let Some(e) = element(id)
        && e.text_content().as_deref() != Some(text)
    {
        e.set_text_content(Some(text));
    }
}

/// Shows or hides element `id`.
pub fn show(id: &str, visible: bool) {
    if let Some(e) = element(id) {
        e.set_hidden(!visible);
    }
}

/// Whether element `id` is on the page and not hidden.
pub fn shown(id: &str) -> bool {
    element(id).is_some_and(|e| !e.hidden())
}

/// Shows `text` in the page's message box (errors a user must read), or hides it.
pub fn message(text: Option<&str>) {
    match text {
        Some(t) => {
            set_text("message", t);
            show("message", true);
        }
        None => show("message", false),
    }
}

/// Milliseconds since the page started (the animation-frame clock).
pub fn now_ms() -> f64 {
    web_sys::window()
        .and_then(|w| w.performance())
        .map_or(0.0, |p| p.now())
}

/// Sets attribute `name` of element `id`, when the page has it.
pub fn set_attr(id: &str, name: &str, value: &str) {
    if let Some(e) = element(id) {
        let _ = e.set_attribute(name, value);
    }
}

/// Makes element `id` hold one button per colour (`data-swatch` its index), each painted in
/// its colour and titled `titles[i]` (made once, then only repainted); those whose colour is
/// `current` get the class `current`.
pub fn set_swatches(id: &str, colours: &[String], titles: &[String], current: &str) {
    let (Some(doc), Some(holder)) = (document(), element(id)) else {
        return;
    };
    let children = holder.children();
    for (i, (colour, title)) in colours.iter().zip(titles).enumerate() {
        let button = match children.item(i as u32) {
            Some(b) => b,
            None => {
                let Ok(b) = doc.create_element("button") else {
                    return;
                };
                let _ = b.set_attribute("data-swatch", &i.to_string());
                if holder.append_child(&b).is_err() {
                    return;
                }
                b
            }
        };
        let _ = button.set_attribute("style", &format!("background:{colour}"));
        let _ = button.set_attribute("title", title);
        let _ = button.set_attribute("class", if colour == current { "current" } else { "" });
    }
}

/// Sets the value of input `id` (the colour chooser), when the page has it.
pub fn set_value(id: &str, value: &str) {
    if let Some(e) = document()
        .and_then(|d| d.get_element_by_id(id))
        .and_then(|e| e.dyn_into::<web_sys::HtmlInputElement>().ok())
        && e.value() != value
    {
        e.set_value(value);
    }
}
