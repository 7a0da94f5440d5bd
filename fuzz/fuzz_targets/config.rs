//! TOML mapper configuration (`map/config.rs`) for every profile, then its conversion to the
//! core's configuration.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    use cloi_host::map::{MapConfig, Profile};
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    for profile in [Profile::Home, Profile::Office, Profile::Airport] {
        if let Ok(c) = MapConfig::from_toml(profile, text, "fuzz.toml") {
            let _ = c.to_toml();
        }
    }
});
