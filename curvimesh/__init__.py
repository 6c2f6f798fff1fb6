"""curvimesh: curvilinear (P2) unit mesh adaptation."""
