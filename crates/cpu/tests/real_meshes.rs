//! The shared scenes' meshes (bunny_69k, igea), camera rays and shadow rays: every hit the
//! reference walk's to the bit, no exception taken.

use bvhtrace_core::Query;
use bvhtrace_cpu::CpuBvh;

mod common;
use common::{every_isa, reference, same};

#[test]
fn real_meshes_give_the_reference_hits_to_the_bit() {
    for name in ["bunny_69k", "igea"] {
        let Some((_, flat, primary, shadow)) = common::scene_rays(name, 320, 240) else {
            println!("{name}: skipped, no shared scenes folder");
            continue;
        };
        let bvh = CpuBvh::from_flat(&flat).unwrap();
        let want = reference(&flat, &primary, Query::Closest);
        let got = every_isa(&bvh, &primary, Query::Closest);
        let differ = got.iter().zip(&want).filter(|(g, w)| !same(g, w)).count();
        let hits = got.iter().filter(|h| h.is_hit()).count();
        assert_eq!(
            differ,
            0,
            "{name}: {differ} of {} primary rays differ",
            primary.len()
        );
        assert!(hits > primary.len() / 10, "{name}: only {hits} hits");
        // Shadow rays: hit or miss as the reference's any-hit and closest-hit walks.
        let any = every_isa(&bvh, &shadow, Query::Any);
        let want_any = reference(&flat, &shadow, Query::Any);
        let want_closest = reference(&flat, &shadow, Query::Closest);
        let got_closest = every_isa(&bvh, &shadow, Query::Closest);
        for i in 0..shadow.len() {
            assert_eq!(
                any[i].is_hit(),
                want_any[i].is_hit(),
                "{name}: shadow ray {i}"
            );
            assert!(
                same(&got_closest[i], &want_closest[i]),
                "{name}: shadow ray {i} closest"
            );
        }
        let occluded = any.iter().filter(|h| h.is_hit()).count();
        println!(
            "{name}: {} primary ({hits} hits), {} shadow ({occluded} occluded): 0 differences",
            primary.len(),
            shadow.len()
        );
    }
}
