"""The studio's Gradio interface: panels, event handlers and the page layout."""
