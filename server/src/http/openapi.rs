//! The OpenAPI 3.1 document (utoipa), served as JSON only: no UI to download.

use axum::response::{IntoResponse, Response};
use utoipa::OpenApi;
use utoipa::openapi::security::{Http, HttpAuthScheme, SecurityScheme};

use super::{jobs, scenes, uploads};

struct BearerAuth;

impl utoipa::Modify for BearerAuth {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme("bearer", SecurityScheme::Http(Http::new(HttpAuthScheme::Bearer)));
    }
}

#[derive(OpenApi)]
#[openapi(
    info(
        title = "voxstream",
        description = "Upload meshes, follow their builds, browse the catalog and stream voxel blocks. \
            Errors are JSON {\"error\": \"...\"}. Write routes need `Authorization: Bearer <token>` when \
            the server has a token; with --protect-read, every route does."
    ),
    paths(
        scenes::list_scenes,
        scenes::get_scene,
        scenes::patch_scene,
        scenes::delete_scene,
        scenes::get_manifest,
        scenes::get_block,
        scenes::get_page,
        scenes::post_batch,
        crate::thumbnail::get_thumbnail,
        uploads::post_scene,
        uploads::tus_options,
        uploads::tus_create,
        uploads::tus_head,
        uploads::tus_patch,
        uploads::tus_delete,
        jobs::list_jobs,
        jobs::get_job,
        jobs::cancel_job,
        jobs::job_events,
        super::healthz,
        super::metrics,
    ),
    modifiers(&BearerAuth),
    tags(
        (name = "scenes", description = "Catalog, manifests and content-addressed blocks"),
        (name = "uploads", description = "POST /api/scenes (single request) and tus 1.0.0 resumable uploads"),
        (name = "jobs", description = "Builds of uploaded meshes"),
        (name = "operations", description = "Health and metrics")
    )
)]
pub struct ApiDoc;

#[utoipa::path(get, path = "/api/openapi.json", tag = "operations",
    responses((status = 200, description = "This document", content_type = "application/json")))]
pub async fn openapi_json() -> Response {
    axum::Json(ApiDoc::openapi()).into_response()
}
