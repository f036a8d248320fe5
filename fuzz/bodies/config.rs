//! Fuzz body: the configuration loader (parse, structure check, validation) on
//! arbitrary UTF-8 text.

/// Loads `data` as configuration text; any result but a panic is fine.
pub fn run(data: &[u8]) {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = compgate_gateway::config::load_str(text, "fuzz");
    }
}
