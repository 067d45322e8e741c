// Swagger UI for PolyDDA, all assets served by the service itself (no CDN).
// "openapi.json" resolves against the /docs page, so a proxy prefix (root_path) works too.
window.ui = SwaggerUIBundle({
  url: "openapi.json",
  dom_id: "#swagger-ui",
  deepLinking: true,
  validatorUrl: null,
  presets: [SwaggerUIBundle.presets.apis],
  layout: "BaseLayout",
});
