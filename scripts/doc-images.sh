#!/usr/bin/env bash
# Regenerates every picture in docs/images from the code that draws it, so the docs show what
# klipcal shows today:
#   pylons.png, soak.png           klipcal's own plots (cargo test --lib doc_images)
#   convergence.png, page-phone.png  an A/B round on klipcal's page in Chromium (tests/it/http.rs)
#   backlash-camera.png            the page during a camera measurement (tests/it/backlash_camera.rs)
#   dialog-mainsail.png, dialog-fluidd.png  an A/B round in the real Mainsail and Fluidd
#                                  (tests/it/frontends.rs)
# The browser tests need the bench (tests/bench/setup.sh) and Chromium; KLIPCAL_BENCH_HOME shares
# an installed bench. Each picture is kept under 150 KB (tests/it/docs.rs checks it).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
export KLIPCAL_DOC_IMAGES=1
bash tests/bench/setup.sh
cargo test -p klipcal --lib doc_images -- --nocapture
cargo test -p klipcal --test it -- --test-threads=2 --nocapture \
    http::in_a_real_browser_readings_are_entered_refused_next_to_the_field_and_solved \
    backlash_camera::the_page_shows_the_newest_frame_with_the_found_nozzle_and_the_cycles \
    frontends::an_ab_round_in_the_real_mainsail \
    frontends::an_ab_round_in_the_real_fluidd
cargo test -p klipcal --test it docs:: -- --test-threads=2
ls -l docs/images
